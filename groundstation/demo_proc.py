"""`covey demo` as a child process, for tests and scripts: start it, read what it prints, stop it.

with DemoProcess(["--vehicles", "3", "--port", "0"]) as demo:
    demo.mesh_endpoint, demo.url, demo.agent_pids
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import sys

from kit.procs import Child

_MESH_RE = re.compile(r"covey demo: mesh (tcp/\S+)")
_URL_RE = re.compile(r"covey demo: ground station at (https?://\S+)")
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
    """Runs `python -m covey_cli demo ARGS`; `__exit__` stops it with SIGINT (then SIGKILL), as
    Ctrl-C would: the demo stops its own children in order."""

    def __init__(
        self, args: list[str], start_timeout_s: float = 60.0, env: dict | None = None
    ) -> None:
        self.args = args
        self.proc = Child(
            [sys.executable, "-u", "-m", "covey_cli", "demo", *args],
            env={**os.environ, **(env or {})},
            own_group=False,  # signals reach the demo only; it stops its agents itself
            stop_signal=signal.SIGINT,
            grace_s=20.0,
            ready=_URL_RE,
            ready_timeout_s=start_timeout_s,
            name="covey demo",
        )

    def __enter__(self) -> DemoProcess:
        self.proc.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _last(self, pattern: re.Pattern[str]) -> str:
        found = [m.group(1) for line in self.proc.lines() if (m := pattern.search(line))]
        return found[-1] if found else ""

    @property
    def mesh_endpoint(self) -> str:
        return self._last(_MESH_RE)

    @property
    def cli_key_file(self) -> str:
        """A station key for `covey cmd` / `covey status` (keyed demos; "" in open mode)."""
        return self._last(_KEY_RE)

    @property
    def url(self) -> str:
        return self._last(_URL_RE)

    @property
    def agent_pids(self) -> dict[int, int]:
        return {
            int(m.group(1)): int(m.group(2))
            for line in self.proc.lines()
            if (m := _PID_RE.search(line))
        }

    @property
    def lines(self) -> list[str]:
        return self.proc.lines()

    def wait_for_line(self, pattern: re.Pattern[str], timeout_s: float) -> str:
        """The next line matching `pattern`; ChildExited (a RuntimeError) if the demo exits
        first, ChildTimeout (a TimeoutError) after timeout_s."""
        return self.proc.wait_for(pattern, timeout_s)

    def output(self) -> str:
        return self.proc.output()

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int | None:
        return self.proc.stop(sig, timeout_s)
