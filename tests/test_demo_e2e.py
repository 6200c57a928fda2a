"""`covey demo` as a real process: vehicles appear on the mesh; SIGINT or its death leaves no orphans."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import wait_until

from comms.mesh import Mesh
from comms.schema import Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess, descendants, process_alive, processes_in_groups
from groundstation.station import GcsConfig, GroundStation

pytestmark = pytest.mark.e2e


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


def run_covey(*argv: str, stdin: str = "") -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "covey_cli", *argv],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_late_station_status_and_cmd_against_a_running_demo():
    with DemoProcess(["--vehicles", "2", "--port", "0"]) as demo:
        ep = demo.mesh_endpoint
        # A second station started late sees the vehicles already there (liveliness history).
        cfg = GcsConfig(mesh=MeshConfig(mode="peer", connect=(ep,)), port=0, gcs_id=2)
        with GroundStation(cfg) as gcs:
            assert wait_until(
                lambda: (
                    {
                        v.vehicle_id
                        for v in gcs.fleet.snapshot(time.time_ns()).vehicles
                        if v.alive and v.state
                    }
                    >= {1, 2}
                ),
                20.0,
            )
        status = run_covey("status", "--connect", ep)
        assert status.returncode == 0, status.stderr
        assert "LANDED" in status.stdout and "ground stations: 1" in status.stdout
        # Secure by default: the demo is keyed, so a command without a station key is refused.
        assert "keyed mode" in demo.output() and demo.cli_key_file, demo.output()
        unsigned = run_covey("cmd", "takeoff", "3", "--to", "1", "--connect", ep)
        assert unsigned.returncode == 1 and "unsigned command" in unsigned.stdout, unsigned.stdout
        key = ("--key-file", demo.cli_key_file)
        ok = run_covey("cmd", "takeoff", "3", "--to", "1,2", "--connect", ep, *key)
        assert ok.returncode == 0, ok.stdout + ok.stderr
        assert ok.stdout.count("accepted") == 2
        missing = run_covey("cmd", "land", "--to", "1,9", "--timeout-s", "1", "--connect", ep, *key)
        assert missing.returncode == 1
        assert "vehicle     9: timeout" in missing.stdout
        refused = run_covey("cmd", "kill", "--to", "all", "--connect", ep, *key, stdin="nope\n")
        assert refused.returncode == 1 and "nothing sent" in refused.stderr
        killed = run_covey("cmd", "kill", "--to", "2", "--connect", ep, *key, stdin="kill\n")
        assert killed.returncode == 0 and "vehicle     2: accepted" in killed.stdout, killed.stdout
