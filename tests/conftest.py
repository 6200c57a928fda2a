"""Shared fixtures: real processes on loopback, always cleaned up."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def wait_until(predicate, timeout_s: float, period_s: float = 0.05) -> bool:
    """Poll `predicate` until it holds or `timeout_s` passes; its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return bool(predicate())


def views_by_id(snapshot) -> dict:
    """vehicle id -> VehicleView of a groundstation.fleet.FleetSnapshot."""
    return {v.vehicle_id: v for v in snapshot.vehicles}


def holds(pred, states) -> bool:
    """pred(states), where a vehicle that is present but not heard from yet (KeyError: it
    happens on a loaded machine) counts as "not yet" rather than as a test error."""
    try:
        return bool(pred(states))
    except KeyError:
        return False


class ProcessGroup:
    """Starts child processes in their own sessions and kills them all at the end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, *args: str, stdout=subprocess.PIPE, **kw) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))
        p = subprocess.Popen(
            [sys.executable, *args],
            cwd=REPO,
            env=env,
            stdout=stdout,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
            **kw,
        )
        self.procs.append(p)
        return p

    def wait_line(self, p: subprocess.Popen, prefix: str, timeout_s: float = 30.0) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                if p.poll() is not None:
                    raise AssertionError(
                        f"process exited ({p.returncode}) before printing {prefix!r}"
                    )
                continue
            if line.startswith(prefix):
                return line
        raise AssertionError(f"no {prefix!r} line within {timeout_s} s")

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            if p.stdout:
                p.stdout.close()


@pytest.fixture
def procs() -> Iterator[ProcessGroup]:
    group = ProcessGroup()
    try:
        yield group
    finally:
        group.close()
