"""`covey demo` as a real process: vehicles appear on the mesh; SIGINT or its death leaves no orphans."""

from __future__ import annotations

import os
import signal
import time

import pytest

from comms.mesh import Mesh
from comms.schema import Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess, descendants, process_alive, processes_in_groups

pytestmark = pytest.mark.e2e


def wait_until(predicate, timeout_s: float, period_s: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_demo_vehicles_appear_and_a_signal_leaves_no_processes(sig):
    with DemoProcess(["--vehicles", "3", "--port", "0"]) as demo:
        assert sorted(demo.agent_pids) == [1, 2, 3]
        states = {}
        cfg = MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))
        with Mesh(cfg) as mesh:
            mesh.subscribe_states(lambda s, _t: states.__setitem__(s.vehicle_id, s))
            pres = mesh.presence()
            assert pres.wait_for(lambda v, g: v >= {1, 2, 3} and g, timeout_s=30.0), demo.output()
            assert wait_until(lambda: set(states) >= {1, 2, 3}, 15.0)
            assert all(s.mode is Mode.LANDED for s in states.values())
        tree = descendants(demo.proc.pid)
        assert set(demo.agent_pids.values()) <= tree
        groups = {os.getpgid(pid) for pid in tree}
        rc = demo.stop(sig)
        assert rc == 0, demo.output()
    assert "covey demo: stopped" in demo.output()
    assert not [pid for pid in tree if process_alive(pid)]
    assert not processes_in_groups(groups)


def test_demo_children_die_with_a_killed_demo():
    with DemoProcess(["--vehicles", "2", "--port", "0"]) as demo:
        tree = descendants(demo.proc.pid)
        assert set(demo.agent_pids.values()) <= tree
        demo.stop(signal.SIGKILL)  # no chance to clean up: PR_SET_PDEATHSIG must do it
        assert wait_until(lambda: not any(process_alive(p) for p in tree), 15.0), [
            p for p in tree if process_alive(p)
        ]
