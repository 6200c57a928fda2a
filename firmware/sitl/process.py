"""Run emulators as separate processes (tests, demos): `with SitlProcess(args) as sitl: ...`."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port nobody holds right now (bind to 0 and read it back)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class SitlProcess:
    """`python -m firmware.sitl ARGS` as a child process; stopped (and reaped) on exit."""

    def __init__(self, args: Sequence[str], stop_timeout_s: float = 5.0) -> None:
        self.args = [sys.executable, "-m", "firmware.sitl", *args]
        self.stop_timeout_s = stop_timeout_s
        self._log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - closed in __exit__
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(
                filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")])
            ),
        }
        self.proc = subprocess.Popen(
            self.args, stdout=self._log, stderr=subprocess.STDOUT, cwd=REPO_ROOT, env=env
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        """Everything the emulator printed so far (for failure messages)."""
        self._log.flush()
        self._log.seek(0)
        return self._log.read()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(self.stop_timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(self.stop_timeout_s)
        return int(self.proc.returncode)

    def __enter__(self) -> SitlProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self._log.close()
