"""Run emulators as separate processes (tests, demos): `with SitlProcess(args) as sitl: ...`."""

from __future__ import annotations

import socket
import sys
from collections.abc import Sequence
from pathlib import Path

from kit.procs import Child, python_env

REPO_ROOT = Path(__file__).resolve().parents[2]


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port nobody holds right now (bind to 0 and read it back)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class SitlProcess(Child):
    """`python -m firmware.sitl ARGS` as a child process, started at once; stopped (SIGTERM,
    then SIGKILL after stop_timeout_s) and reaped on exit. `output()`: what it printed."""

    def __init__(self, args: Sequence[str], stop_timeout_s: float = 5.0) -> None:
        super().__init__(
            [sys.executable, "-m", "firmware.sitl", *args],
            cwd=REPO_ROOT,
            env=python_env(REPO_ROOT),
            grace_s=stop_timeout_s,
            name="covey sitl " + " ".join(args[:2]),
        )
        self.start()
