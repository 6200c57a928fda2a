"""vehicle_states of one row (an agent's every tick: `_one_vehicle_state`, Python floats)
equals the general path (`vehicle_states_rows`, the arrays) exactly: the same fields, of the
same types, every float the same bits (NaN and -0.0 included), for every mode, flag, goal (a NaN
target: none), clamped battery and sigma, wrapped heading, mission progress and lost link; and
the shell's `_states` of one row (its seq and bits in Python ints) equals the arrays' too."""

from __future__ import annotations

import dataclasses
import math
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from agent import shell_rows
from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.hosts import Agent
from agent.mission import LocalItem, MissionRun, RunStatus
from agent.neighbours import NeighbourSnapshot
from agent.shell_config import AgentConfig
from agent.shell_rows import stale_rows, vehicle_states, vehicle_states_rows
from comms.mesh import Mesh
from comms.schema import MissionItemKind, Mode, StateFlag, VehicleState
from comms.session import embedded_router, free_tcp_port

FIELDS = [f.name for f in dataclasses.fields(VehicleState)]
MODES = list(Mode)
SPECIAL_HEADINGS = [math.pi, -math.pi, 3 * math.pi, -7.5, 1e300, -1e-320, -0.0, 0.0, math.nan]
SPECIAL_CLAMPED = [-0.0, 0.0, -1e-300, math.nan, math.inf, -math.inf, 100.0, 1000.0, 1e6]


def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


def same(a: VehicleState, b: VehicleState) -> None:
    """Field by field: the same type, floats the same bits, the rest equal."""
    assert type(a) is type(b)
    assert set(vars(a)) == set(vars(b))
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert type(x) is type(y), name
        if isinstance(x, tuple):
            assert len(x) == len(y), name
            for u, v in zip(x, y, strict=True):
                assert type(u) is type(v), name
                assert _bits(u) == _bits(v), (name, x, y)
        elif isinstance(x, float):
            assert _bits(x) == _bits(y), (name, x, y)
        else:
            assert x == y, name
    if not any(math.isnan(v) for v in _floats(a)):
        assert a == b


def _floats(s: VehicleState) -> list[float]:
    return [
        *s.pos_ned_m,
        *s.vel_ned_m_s,
        *s.goal_ned_m,
        s.heading_rad,
        s.battery_pct,
        s.pos_sigma_m,
    ]


def _pick(rng: np.random.Generator, special: list[float], share: float, draw: float) -> float:
    return special[int(rng.integers(len(special)))] if rng.random() < share else draw


def _mission(rng: np.random.Generator) -> MissionRun | None:
    if rng.random() < 0.3:
        return None
    k = int(rng.integers(1, 6))
    items = tuple(LocalItem(MissionItemKind.WAYPOINT, (float(j), 0.0, -5.0)) for j in range(k))
    run = MissionRun(1, 1, items)
    run.status = list(RunStatus)[int(rng.integers(len(RunStatus)))]
    index = int(rng.integers(0, k))
    run.index = np.int64(index) if rng.random() < 0.2 else index  # as a numpy int too
    return run


def _world(rng: np.random.Generator, n: int):
    """(core, obs, pos_sigma_m, ids, seq, bits) of n vehicles: a real FlightCore in random
    states, the telemetry and the shell's columns with the edge cases drawn now and then."""
    core = FlightCore(CoreConfig(), n, now_s=0.0)
    for i in range(n):
        core.mode[i] = int(MODES[int(rng.integers(len(MODES)))])
        for where in (core.goal_m, core.hold_m):
            pick = rng.random()
            if pick < 0.2:
                where[i] = np.nan
            elif pick < 0.25:  # a goal with NaN past its first axis: still a goal
                where[i] = (float(rng.uniform(-500, 500)), np.nan, -10.0)
            else:
                where[i] = rng.uniform(-500, 500, 3)
        core.heading_rad[i] = _pick(rng, SPECIAL_HEADINGS, 0.2, float(rng.uniform(-10, 10)))
        core.failsafes[i].flags = StateFlag(int(rng.integers(0, 32)) & ~int(StateFlag.HAS_GOAL))
        core.missions[i] = _mission(rng)
    obs = Observed(
        pos_m=rng.uniform(-500, 500, (n, 3)),
        vel_m_s=rng.uniform(-20, 20, (n, 3)) * (rng.random((n, 1)) < 0.8),
        armed=rng.random(n) < 0.6,
        in_air=rng.random(n) < 0.5,
        battery_pct=np.array(
            [_pick(rng, SPECIAL_CLAMPED, 0.2, float(rng.uniform(-20, 130))) for _ in range(n)]
        ),
        link_ok=rng.random(n) < 0.7,
    )
    sigma = np.array(
        [_pick(rng, SPECIAL_CLAMPED, 0.3, float(rng.uniform(-5, 1200))) for _ in range(n)]
    )
    ids = rng.choice(np.arange(1, 2000), n, replace=False).astype(
        np.int32 if rng.random() < 0.3 else np.int64
    )
    seq = rng.integers(0, 2**32, n)
    shell = [StateFlag.OPEN_MODE, StateFlag.FILTER_ACTIVE, StateFlag.NEIGHBOURS_STALE]
    per_row = rng.integers(0, 2, (n, 3)) * np.array([int(f) for f in shell])
    pick = rng.random()
    if pick < 0.4:  # one int for every row, as the shell's one-row path gives it
        bits: np.ndarray | int = int(per_row[0].sum())
    elif pick < 0.5:
        bits = StateFlag(int(per_row[0].sum()))
    else:
        bits = per_row.sum(axis=1).astype(np.int32 if pick < 0.7 else np.int64)
    return core, obs, sigma, ids, seq, bits


@pytest.mark.parametrize("seed", range(400))
def test_one_row_equals_the_rows_path(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 1 if seed % 3 else int(rng.integers(2, 5))
    core, obs, sigma, ids, seq, bits = _world(rng, n)
    rows = np.array([int(rng.integers(n))])
    stamp_ns = int(rng.integers(0, 2**63))
    fast = shell_rows._one_vehicle_state(core, obs, sigma, ids, seq, rows, bits, stamp_ns)
    assert fast is not None  # the plain inputs take the fast path
    with np.errstate(invalid="ignore"):  # np.remainder of inf
        (want,) = vehicle_states_rows(core, obs, sigma, ids, seq, rows, bits, stamp_ns)
    same(fast, want)
    (got,) = vehicle_states(core, obs, sigma, ids, seq, rows, bits, stamp_ns)
    same(got, want)


def test_the_cases_that_matter_are_drawn() -> None:
    """The seeds above draw every case: a goal and none, each mode, clamped battery and sigma
    (both sides, NaN, -0.0), a heading to wrap, a lost link, each mission status, flags."""
    seen: set[str] = set()
    for seed in range(400):
        rng = np.random.default_rng(seed)
        n = 1 if seed % 3 else int(rng.integers(2, 5))
        core, obs, sigma, ids, seq, bits = _world(rng, n)
        r = int(rng.integers(n))
        (s,) = vehicle_states_rows(core, obs, sigma, ids, seq, np.array([r]), bits, 1)
        b, g, h = obs.battery_pct[r], sigma[r], core.heading_rad[r]
        run = core.missions[r]
        seen |= {
            "goal" if s.flags & StateFlag.HAS_GOAL else "no goal",
            f"mode {s.mode.name}",
            "battery low" if b < 0 else "battery high" if b > 100 else "",
            "sigma low" if g < 0 else "sigma high" if g > 1000 else "",
            "nan" if math.isnan(b) or math.isnan(g) or math.isnan(h) else "",
            "-0" if _bits(b) == _bits(-0.0) or _bits(g) == _bits(-0.0) else "",
            "wrapped" if abs(h) > math.pi else "",
            "link lost" if s.flags & StateFlag.FAILSAFE_LINK_LOST else "",
            "no mission" if run is None else f"mission {run.status.name}",
            "failsafe" if s.flags & StateFlag.FAILSAFE_GCS_LOST else "",
            "stale" if s.flags & StateFlag.NEIGHBOURS_STALE else "",
        }
    want = {"goal", "no goal", "battery low", "battery high", "sigma low", "sigma high"}
    want |= {"nan", "-0", "wrapped", "link lost", "no mission", "failsafe", "stale"}
    want |= {f"mode {m.name}" for m in MODES} | {f"mission {s.name}" for s in RunStatus}
    assert seen >= want, want - seen


def test_one_row_does_not_take_the_rows_path(monkeypatch: pytest.MonkeyPatch) -> None:
    core, obs, sigma, ids, seq, bits = _world(np.random.default_rng(1), 1)

    def general(*args):
        raise AssertionError("the rows' path was taken")

    monkeypatch.setattr(shell_rows, "vehicle_states_rows", general)
    assert len(vehicle_states(core, obs, sigma, ids, seq, np.array([0]), bits, 5)) == 1


@pytest.mark.parametrize("seed", range(20))
def test_other_inputs_take_the_rows_path(seed: int) -> None:
    """Several rows, and one row whose columns are not the plain ones (a float32 heading, an
    integer battery or sigma, float bits, a SimpleNamespace of lists): the rows' path answers."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 5))
    core, obs, sigma, ids, seq, bits = _world(rng, n)
    rows = np.flatnonzero(rng.random(n) < 0.7)
    with np.errstate(invalid="ignore"):
        many = vehicle_states(core, obs, sigma, ids, seq, rows, bits, 7)
        want = vehicle_states_rows(core, obs, sigma, ids, seq, rows, bits, 7)
    assert len(many) == len(want)
    for a, b in zip(many, want, strict=True):
        same(a, b)
    row = np.array([0])
    f8 = core.heading_rad
    with np.errstate(over="ignore"):
        f4 = f8.astype(np.float32)
    cases = {
        "float32 heading": (f4, obs, sigma, bits),
        "integer battery": (f8, dataclasses.replace(obs, battery_pct=np.full(n, 50)), sigma, bits),
        "integer sigma": (f8, obs, np.full(n, 3), bits),
        "float bits": (f8, obs, sigma, np.full(n, 8.0)),
    }
    for name, (heading, o, g, b) in cases.items():
        core.heading_rad = heading
        assert shell_rows._one_vehicle_state(core, o, g, ids, seq, row, b, 7) is None, name
        with np.errstate(invalid="ignore"):
            (got,) = vehicle_states(core, o, g, ids, seq, row, b, 7)
            (want_one,) = vehicle_states_rows(core, o, g, ids, seq, row, b, 7)
        same(got, want_one)
    core.heading_rad = f8
    lists = SimpleNamespace(**{k: list(v) for k, v in vars(obs).items() if v is not None})
    assert shell_rows._one_vehicle_state(core, lists, sigma, ids, seq, row, bits, 7) is None


# -- the shell's _states -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def agent():
    """An in-process agent (one simulated vehicle) on a real mesh whose clock stands still."""
    cfg = AgentConfig(vehicle_id=3, failsafe=FailsafeConfig(require_gcs=False))
    mesh_cfg = embedded_router(free_tcp_port(), fleet="onerow")
    with (
        Mesh(mesh_cfg, clock_ns=lambda: 1_234_567_890) as mesh,
        Agent(cfg, SimBackend(SimConfig(), now_s=0.0), mesh, clock_s=lambda: 0.0) as ag,
    ):
        yield ag


def _reference_states(ag: Agent, rows: np.ndarray, obs: Observed, ext: NeighbourSnapshot):
    """`VehicleShell._states` as the arrays make it (the shell's code before its one-row path)."""
    ag.seq[rows] = (ag.seq[rows] + 1) & 0xFFFFFFFF
    stale = stale_rows(ag.slowed, obs.pos_m, ext, ag.cfg.neighbours.vertical_band_m)
    bits = (
        int(ag.flags)
        | np.where(ag.filtered, int(StateFlag.FILTER_ACTIVE), 0)
        | np.where(stale, int(StateFlag.NEIGHBOURS_STALE), 0)
    )
    sigma = ag.vehicles.pos_sigma_m
    return vehicle_states_rows(ag.core, obs, sigma, ag.ids, ag.seq, rows, bits, ag.mesh.clock_ns())


def _snapshot(rng: np.random.Generator, own: np.ndarray) -> NeighbourSnapshot:
    """Neighbours around `own`, some of them stale, some within the vertical band of it."""
    k = int(rng.integers(0, 8))
    pos = np.column_stack(
        [own[:2] + rng.uniform(-50, 50, (k, 2)), own[2] + rng.uniform(-30, 30, k)]
    )
    ids = tuple(int(i) for i in rng.choice(np.arange(10, 100), k, replace=False))
    stale = tuple(i for i in ids if rng.random() < 0.4)
    return NeighbourSnapshot(pos, np.zeros((k, 3)), np.zeros(k), ids, np.zeros(k), stale)


@pytest.mark.parametrize("seed", range(60))
def test_states_of_one_row_equal_the_arrays(agent: Agent, seed: int) -> None:
    rng = np.random.default_rng(seed)
    ag = agent
    obs = ag.vehicles.read()
    obs = dataclasses.replace(
        obs, pos_m=obs.pos_m + rng.uniform(-5, 5, (1, 3)), link_ok=rng.random(1) < 0.7
    )
    ext = _snapshot(rng, obs.pos_m[0])
    ag.filtered[:] = rng.random(1) < 0.5
    ag.slowed[:] = rng.random(1) < 0.3
    ag.flags = StateFlag.OPEN_MODE if rng.random() < 0.5 else StateFlag.NONE
    ag.seq[:] = int(rng.integers(0, 2**32)) if rng.random() < 0.5 else 2**32 - 1  # wraps
    rows = np.array([0])
    seq0 = ag.seq.copy()
    (got,) = ag._states(rows, obs, ext)
    seq1 = ag.seq.copy()
    ag.seq[:] = seq0
    (want,) = _reference_states(ag, rows, obs, ext)
    np.testing.assert_array_equal(seq1, ag.seq, strict=True)
    same(got, want)
