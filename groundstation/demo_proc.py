"""`covey demo` as a child process, for tests and scripts: start it, read what it prints, stop it.

with DemoProcess(["--vehicles", "3", "--port", "0"]) as demo:
    demo.mesh_endpoint, demo.url, demo.agent_pids
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time

_MESH_RE = re.compile(r"covey demo: mesh (tcp/\S+)")
_URL_RE = re.compile(r"covey demo: ground station at (http://\S+)")
_PID_RE = re.compile(r"covey demo: vehicle (\d+) pid (\d+)")
_KEY_RE = re.compile(r"covey demo: mesh .*--key-file (\S+)\)")


def process_alive(pid: int) -> bool:
    """True if `pid` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False


def descendants(pid: int) -> set[int]:
    """Every live descendant of `pid` (from /proc/<pid>/task/*/children)."""
    found: set[int] = set()
    stack = [pid]
    while stack:
        p = stack.pop()
        with contextlib.suppress(FileNotFoundError, ProcessLookupError):
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    for child in map(int, f.read().split()):
                        if child not in found:
                            found.add(child)
                            stack.append(child)
    return found


def processes_in_groups(pgids: set[int]) -> set[int]:
    """Live processes whose process group is one of `pgids`."""
    out = set()
    for name in os.listdir("/proc"):
        if name.isdigit():
            with contextlib.suppress(FileNotFoundError, ProcessLookupError, IndexError, ValueError):
                with open(f"/proc/{name}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                if fields[0] != "Z" and int(fields[2]) in pgids:
                    out.add(int(name))
    return out


class DemoProcess:
    """Runs `python -m covey_cli demo ARGS`; `__exit__` stops it with SIGINT (then SIGKILL)."""

    def __init__(
        self, args: list[str], start_timeout_s: float = 60.0, env: dict | None = None
    ) -> None:
        self.args = args
        self.start_timeout_s = start_timeout_s
        self.env = env
        self.lines: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        self.proc: subprocess.Popen | None = None
        self.mesh_endpoint = ""
        self.cli_key_file = ""
        """A station key for `covey cmd` / `covey status` (keyed demos; "" in open mode)."""
        self.url = ""
        self.agent_pids: dict[int, int] = {}

    def __enter__(self) -> DemoProcess:
        self.proc = subprocess.Popen(
            [sys.executable, "-u", "-m", "covey_cli", "demo", *self.args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            env={**os.environ, **(self.env or {})},
        )
        threading.Thread(target=self._read, daemon=True).start()
        try:
            self.wait_for_line(_URL_RE, self.start_timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self._queue.put(None)

    def _take(self, line: str) -> None:
        self.lines.append(line)
        if m := _MESH_RE.search(line):
            self.mesh_endpoint = m.group(1)
        if m := _KEY_RE.search(line):
            self.cli_key_file = m.group(1)
        if m := _URL_RE.search(line):
            self.url = m.group(1)
        if m := _PID_RE.search(line):
            self.agent_pids[int(m.group(1))] = int(m.group(2))

    def wait_for_line(self, pattern: re.Pattern[str], timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                line = self._queue.get(timeout=max(0.01, left))
            except queue.Empty:
                line = ""
            if line is None:
                raise RuntimeError("covey demo exited:\n" + "\n".join(self.lines[-30:]))
            if line:
                self._take(line)
                if pattern.search(line):
                    return line
            if time.monotonic() >= deadline:
                raise TimeoutError(
                    f"no line matching {pattern.pattern!r}:\n" + "\n".join(self.lines[-30:])
                )

    def output(self) -> str:
        with contextlib.suppress(queue.Empty):
            while (line := self._queue.get_nowait()) is not None:
                self._take(line)
        return "\n".join(self.lines)

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode
