"""Child processes: start one, wait for its READY line, keep what it prints, stop it.

    with Child([sys.executable, "tests/mesh_node.py", "7447"], ready="READY") as node:
        node.wait_for("STATE 1 ", timeout_s=20)
    # stopped: SIGTERM to its process group, SIGKILL after grace_s, leftovers of the group killed

    with ChildGroup(prefix=[sys.executable], cwd=REPO, env=python_env(REPO)) as kids:
        a, b = kids.start("-m", "covey_cli", "agent", "--id", "1"), kids.start(...)

Every child runs in its own process group (unless own_group=False), so stopping it also stops
whatever it started. Its output is read by a thread as it comes, so a chatty child never blocks
on a full pipe, and `wait_for` has a real timeout. One module for tests, benchmarks, the demo
and the emulators; it lives in kit/ (it imports nothing of covey) so that every layer may use it.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

PR_SET_PDEATHSIG = 1
TAIL_LINES = 30
"""Lines of a child's output quoted in an error about it."""


class ChildError(RuntimeError):
    """A child did not do what was expected; the message quotes its last lines of output."""


class ChildExited(ChildError):
    """The child closed its output (it exited) before printing the line waited for."""


class ChildTimeout(ChildError, TimeoutError):
    """The line waited for did not come in time."""


def python_env(repo: str | os.PathLike, **extra: str) -> dict[str, str]:
    """This process's environment for a Python child that imports from `repo`, unbuffered."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", **extra)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")]))
    return env


def _die_with_parent() -> None:
    """preexec_fn: SIGTERM this child when its parent dies, however it dies (Linux)."""
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


_STREAMS: dict[str, Any] = {
    "capture": subprocess.PIPE,
    "inherit": None,
    "discard": subprocess.DEVNULL,
    "merge": subprocess.STDOUT,
}


class Child:
    """One child process; a context manager that starts it (waiting for `ready` if given) and
    stops it on exit.

    output: "capture" (read into `lines()`; `wait_for` works), "inherit", "discard", or an
        open file. stderr: "merge" (into output), "inherit" or "discard".
    own_group: the child leads its own process group; signals go to the whole group.
    stop_signal, grace_s: `stop` sends stop_signal, then SIGKILL after grace_s.
    die_with_parent: the kernel SIGTERMs the child if this process dies (PR_SET_PDEATHSIG).
    keep_lines: the most recent lines kept in memory.
    """

    def __init__(
        self,
        argv: Sequence[str | os.PathLike],
        *,
        cwd: str | os.PathLike | None = None,
        env: Mapping[str, str] | None = None,
        output: str | IO[str] = "capture",
        stderr: str = "merge",
        own_group: bool = True,
        stop_signal: int = signal.SIGTERM,
        grace_s: float = 5.0,
        die_with_parent: bool = False,
        ready: str | re.Pattern[str] | None = None,
        ready_timeout_s: float = 30.0,
        keep_lines: int = 20_000,
        name: str | None = None,
    ) -> None:
        self.argv = [str(a) for a in argv]
        self.cwd, self.env = cwd, None if env is None else dict(env)
        self.output_to, self.stderr_to = output, stderr
        self.own_group, self.stop_signal, self.grace_s = own_group, stop_signal, grace_s
        self.die_with_parent = die_with_parent
        self.ready, self.ready_timeout_s = ready, ready_timeout_s
        self.keep_lines = keep_lines
        self.name = name or " ".join(
            Path(a).name if i == 0 else a for i, a in enumerate(self.argv[:5])
        )
        self.proc: subprocess.Popen[str] | None = None
        self._cond = threading.Condition()
        self._lines: list[str] = []
        self._base = 0  # absolute index of self._lines[0] (older lines were dropped)
        self._cursor = 0  # absolute index of the next line wait_for looks at
        self._eof = False
        self._reader: threading.Thread | None = None

    # -- starting --------------------------------------------------------------------------------
    def start(self) -> Child:
        """Start the child (once; a second call does nothing)."""
        if self.proc is not None:
            return self
        out = _STREAMS[self.output_to] if isinstance(self.output_to, str) else self.output_to
        self.proc = subprocess.Popen(
            self.argv,
            cwd=self.cwd,
            env=self.env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=_STREAMS[self.stderr_to],
            text=True,
            errors="replace",
            process_group=0 if self.own_group else None,
            preexec_fn=_die_with_parent if self.die_with_parent else None,
        )
        if self.proc.stdout is not None:
            self._reader = threading.Thread(target=self._read, name=f"out:{self.name}", daemon=True)
            self._reader.start()
        else:
            self._eof = True
        return self

    def __enter__(self) -> Child:
        self.start()
        if self.ready is not None:
            try:
                self.wait_for(self.ready, self.ready_timeout_s)
            except BaseException:
                self.stop()
                raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- output ----------------------------------------------------------------------------------
    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        stream = self.proc.stdout
        try:
            for line in stream:
                with self._cond:
                    self._lines.append(line.rstrip("\n"))
                    if len(self._lines) > self.keep_lines:
                        drop = len(self._lines) - self.keep_lines
                        del self._lines[:drop]
                        self._base += drop
                    self._cond.notify_all()
        except (OSError, ValueError):  # the stream was closed under us
            pass
        finally:
            with self._cond:
                self._eof = True
                self._cond.notify_all()
            with contextlib.suppress(OSError):
                stream.close()

    def lines(self) -> list[str]:
        """What the child printed so far (the most recent keep_lines lines)."""
        with self._cond:
            return list(self._lines)

    def output(self) -> str:
        """What the child printed so far, as one text."""
        return "\n".join(self.lines())

    def _tail(self) -> str:
        return "\n".join(self.lines()[-TAIL_LINES:])

    def wait_for(self, pattern: str | re.Pattern[str], timeout_s: float = 30.0) -> str:
        """The next line (after those already matched) that starts with `pattern` (a string)
        or that `pattern` (a regex) matches. Raises ChildExited when the child's output ends
        first, ChildTimeout after timeout_s; both quote its last lines."""
        if self.proc is None or (self.proc.stdout is None and self._reader is None):
            raise ValueError(f"{self.name}: output is not captured (output='capture')")
        if isinstance(pattern, str):
            what, match = repr(pattern), lambda line: line.startswith(pattern)
        else:
            what, match = f"/{pattern.pattern}/", lambda line: pattern.search(line) is not None
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                while self._cursor < self._base + len(self._lines):
                    self._cursor = max(self._cursor, self._base)
                    line = self._lines[self._cursor - self._base]
                    self._cursor += 1
                    if match(line):
                        return line
                if self._eof:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ChildTimeout(
                        f"{self.name}: no line {what} within {timeout_s:g} s; its last lines:\n"
                        + self._tail()
                    )
                self._cond.wait(left)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=2.0)
        raise ChildExited(
            f"{self.name} exited ({self.proc.returncode}) before printing {what}; its last "
            "lines:\n" + self._tail()
        )

    def wait_output(self, timeout_s: float | None = None) -> str:
        """Wait for the child to exit (subprocess.TimeoutExpired after timeout_s); everything
        it printed."""
        assert self.proc is not None, "not started"
        self.proc.wait(timeout=timeout_s)
        if self._reader is not None:
            self._reader.join(timeout=5.0)
        return self.output()

    # -- the process -------------------------------------------------------------------------------
    @property
    def pid(self) -> int:
        assert self.proc is not None, "not started"
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def poll(self) -> int | None:
        return self.returncode

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def wait(self, timeout: float | None = None) -> int:
        """The exit status; subprocess.TimeoutExpired if it is still running after `timeout`."""
        assert self.proc is not None, "not started"
        return self.proc.wait(timeout=timeout)

    def send_signal(self, sig: int) -> None:
        """`sig` to the child itself (not its group), if it is still running."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)

    def signal(self, sig: int) -> None:
        """`sig` to the child's process group (own_group) or to the child."""
        if self.proc is None:
            return
        if self.own_group:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)
        else:
            self.send_signal(sig)

    def kill(self) -> None:
        """SIGKILL now (the whole group with own_group)."""
        self.signal(signal.SIGKILL)

    def stop(self, sig: int | None = None, grace_s: float | None = None) -> int | None:
        """Send `sig` (default stop_signal), wait up to grace_s, then SIGKILL; with own_group
        also kill what is left of its group. Returns the exit status (None: never started)."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.signal(self.stop_signal if sig is None else sig)
        self._finish(time.monotonic() + (self.grace_s if grace_s is None else grace_s))
        return self.proc.returncode

    def _finish(self, deadline: float) -> None:
        """Wait for the signalled child until `deadline`, then SIGKILL; reap it."""
        assert self.proc is not None
        try:
            self.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.kill()
            self.proc.wait()
        if self.own_group:  # whatever the child started, still in its group
            self.kill()
        if self._reader is not None:
            self._reader.join(timeout=1.0)


class ChildGroup:
    """Several children with shared settings, stopped together on exit: stop_signal to all,
    then SIGKILL to those still running grace_s later."""

    def __init__(self, *, prefix: Sequence[str] = (), **defaults: Any) -> None:
        self.prefix = list(prefix)
        self.defaults = defaults
        self.children: list[Child] = []

    def start(self, *argv: str | os.PathLike, **overrides: Any) -> Child:
        """Start prefix + argv with the group's settings (and `overrides`); it is stopped with
        the group."""
        child = Child([*self.prefix, *argv], **{**self.defaults, **overrides})
        self.children.append(child)
        child.start()
        return child

    def __iter__(self) -> Iterator[Child]:
        return iter(list(self.children))

    def __enter__(self) -> ChildGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        started = [c for c in self.children if c.proc is not None]
        deadlines = []
        for c in started:
            if c.proc is not None and c.proc.poll() is None:
                c.signal(c.stop_signal)
            deadlines.append(time.monotonic() + c.grace_s)
        for c, deadline in zip(started, deadlines, strict=True):
            c._finish(deadline)
        self.children.clear()
