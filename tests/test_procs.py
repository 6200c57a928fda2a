"""kit/procs.py: the one way covey starts, watches and stops a child process."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from conftest import wait_until

from kit.procs import Child, ChildExited, ChildGroup, ChildTimeout


def py(code: str) -> list[str]:
    return [sys.executable, "-u", "-c", code]


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_ready_line_then_output_is_captured_and_the_exit_status_kept() -> None:
    code = "print('starting'); print('READY port 7'); print('STATE 1 5'); import sys; sys.exit(3)"
    with Child(py(code), ready="READY") as c:
        assert c.wait_for(re.compile(r"STATE 1 (\d+)"), 5.0) == "STATE 1 5"
        assert c.wait(5.0) == 3
    assert c.lines() == ["starting", "READY port 7", "STATE 1 5"] and c.returncode == 3


def test_a_child_that_never_says_ready_is_a_clear_timeout_and_is_stopped() -> None:
    child = Child(
        py("print('booting', flush=True); import time; time.sleep(60)"),
        ready="READY",
        ready_timeout_s=1.0,
    )
    t0 = time.monotonic()
    with pytest.raises(ChildTimeout) as exc, child:
        pass
    message = str(exc.value)
    assert "no line 'READY' within" in message and "booting" in message, message
    assert isinstance(exc.value, TimeoutError)
    assert time.monotonic() - t0 < child.ready_timeout_s + child.grace_s + 5
    assert not child.alive()


def test_waiting_on_a_child_that_exits_first_says_so() -> None:
    said = r"(?s)exited \(0\) before printing 'READY'.*oops"
    with (
        Child(py("print('oops: no config')"), grace_s=1.0) as c,
        pytest.raises(ChildExited, match=said),
    ):
        c.wait_for("READY", timeout_s=10.0)


def test_a_child_that_ignores_sigterm_is_killed_after_the_grace_period() -> None:
    code = (
        "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
        "print('READY', flush=True); time.sleep(60)"
    )
    with Child(py(code), ready="READY", grace_s=0.5) as c:
        pid = c.pid
    assert c.returncode == -signal.SIGKILL
    assert not alive(pid)


def test_a_polite_child_gets_sigterm_and_exits_by_itself() -> None:
    code = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *_: (print('bye', flush=True), sys.exit(0)))\n"
        "print('READY', flush=True); time.sleep(60)"
    )
    with Child(py(code), ready="READY", grace_s=10.0) as c:
        pass
    assert c.returncode == 0 and c.lines()[-1] == "bye"


def test_stopping_a_child_also_stops_what_it_started() -> None:
    code = (
        "import subprocess, sys, time\n"
        "g = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        "print('READY', g.pid, flush=True); time.sleep(60)"
    )
    with Child(py(code), ready="READY", grace_s=2.0) as c:
        grandchild = int(c.lines()[-1].split()[1])
        assert alive(grandchild)
    assert wait_until(lambda: not alive(grandchild), 5.0)


def test_a_chatty_child_never_blocks_and_only_recent_lines_are_kept() -> None:
    code = "for i in range(200000): print('x' * 50, i)\nprint('DONE')"
    with Child(py(code), keep_lines=100) as c:
        assert c.wait_for("DONE", timeout_s=60.0) == "DONE"
        assert len(c.lines()) == 100


def test_uncaptured_output_cannot_be_waited_for() -> None:
    with Child(py("pass"), output="discard") as c, pytest.raises(ValueError, match="capture"):
        c.wait_for("READY", 1.0)


def test_a_group_stops_every_child_together() -> None:
    code = "import time; print('READY', flush=True); time.sleep(60)"
    t0 = time.monotonic()
    with ChildGroup(prefix=[sys.executable, "-u", "-c"], grace_s=3.0) as g:
        kids = [g.start(code) for _ in range(3)]
        for k in kids:
            k.wait_for("READY", 10.0)
        pids = [k.pid for k in kids]
    assert not any(alive(p) for p in pids) and time.monotonic() - t0 < 15.0
    assert all(k.returncode == -signal.SIGTERM for k in kids)


def test_wait_output_and_a_timeout() -> None:
    c = Child(py("import time; time.sleep(0.2); print('FLOOD sent 3')")).start()
    assert c.wait_output(timeout_s=10.0).strip() == "FLOOD sent 3"
    slow = Child(py("import time; time.sleep(60)")).start()
    with pytest.raises(subprocess.TimeoutExpired):
        slow.wait_output(timeout_s=0.2)
    slow.stop()
    assert not slow.alive()


def test_die_with_parent_reaps_a_child_whose_parent_is_killed() -> None:
    """The demo's agents: SIGKILL the parent, the kernel SIGTERMs the child."""
    code = (
        "import sys, time\nfrom kit.procs import Child\n"
        "c = Child([sys.executable, '-c', 'import time; time.sleep(60)'], output='inherit', "
        "die_with_parent=True).start()\n"
        "print('READY', c.pid, flush=True); time.sleep(60)"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with Child(py(code), ready="READY", env=env, own_group=False) as parent:
        child = int(parent.lines()[-1].split()[1])
        parent.stop(signal.SIGKILL)
    assert wait_until(lambda: not alive(child), 10.0)
