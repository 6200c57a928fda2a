"""Shared fixtures: real processes on loopback, always cleaned up."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from kit.procs import ChildGroup, python_env

REPO = Path(__file__).resolve().parent.parent
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Scripts that run covey's Python (comms/zenoh_configs/make_certs.sh) run this one: a git
# worktree has no .venv of its own, and the system python3 has no zenoh.
os.environ.setdefault("COVEY_PYTHON", sys.executable)


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


@pytest.fixture
def procs() -> Iterator[ChildGroup]:
    """Python children (`procs.start("tests/mesh_node.py", ...)`) in their own process groups,
    output captured (`child.wait_for("READY")`), all killed at the end of the test (no grace:
    nothing they hold needs a clean shutdown, and a kill is fastest)."""
    with ChildGroup(prefix=[sys.executable], cwd=REPO, env=python_env(REPO), grace_s=0.0) as g:
        yield g


@pytest.fixture
def mesh_trio(request: pytest.FixtureRequest):
    """A router (the station's side) and two peers on a free loopback port (multicast scouting
    off), in the test module's FLEET. The router has no cell relay: its tests step simulated
    time faster than the wall clock, by which a relay sends (tests/test_comms_relay.py)."""
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    fleet = getattr(request.module, "FLEET", "covey")
    port = free_tcp_port()
    with (
        Mesh(replace(embedded_router(port, fleet=fleet), cell_relay_period_s=None)) as hub,
        Mesh(embedded_peer(port, fleet=fleet)) as a,
        Mesh(embedded_peer(port, fleet=fleet)) as b,
    ):
        yield hub, a, b


def keyed_agent_argv(authority, vehicle_id: int) -> list[str]:
    """The start of a child `covey agent` command line for one keyed vehicle: its id and the
    key file `authority` issued for it (append the test's own flags)."""
    from comms.schema import Role

    return [
        "-m",
        "covey_cli",
        "agent",
        "--id",
        str(vehicle_id),
        "--key-file",
        str(authority.member_path(Role.VEHICLE, vehicle_id)),
    ]


@pytest.fixture(scope="session")
def fuzz_drivers():
    """(sanitized, plain) host drivers of the C core for the shipped weights
    (firmware/host/covey_driver.c): ASan + UBSan and the optimised build, whose outputs a fuzz
    test compares bit for bit. Skips where the C compiler cannot build with sanitizers."""
    from firmware import hostbuild

    header = hostbuild.header_for(hostbuild.SHIPPED_NPZ)
    try:
        asan = hostbuild.build_driver(header, sanitize=True)
    except RuntimeError as e:
        if "sanitize" in str(e) or "asan" in str(e).lower():
            pytest.skip(f"the C compiler cannot build with sanitizers: {str(e)[-300:]}")
        raise
    return asan, hostbuild.build_driver(header)


SLOW_MARKS = ("e2e", "browser", "slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under pytest-xdist (`make test` runs `-n 2 --dist loadfile --no-loadscope-reorder`),
    hand out the files with the most slow tests first, so that no long file starts last and
    leaves one worker alone at the end. Each file's tests keep their order (several files share
    one fleet across their tests); a plain `pytest` run keeps the collection order."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    weight: dict[str, int] = {}
    for item in items:
        slow = any(item.get_closest_marker(m) for m in SLOW_MARKS)
        weight[item.nodeid.split("::")[0]] = weight.get(item.nodeid.split("::")[0], 0) + slow
    # sorted() is stable: files of equal weight, and the tests within each, keep their order
    items.sort(key=lambda item: -weight[item.nodeid.split("::")[0]])
