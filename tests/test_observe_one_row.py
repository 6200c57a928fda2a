"""One vehicle's tick in Python floats (`FlightCore._observe_one`, `guided_rows` at N = 1,
`FailsafeConfig.calm_one`: what every agent runs) against the array paths of any number of rows
(`_observe_rows`, `_guided_rows`, `calm_rows`, the references): the same actions, modes, goals,
notes and failsafe state, tick by tick, on random telemetry and commands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.failsafe import FENCE_TIE_M, FailsafeConfig, Failsafes
from agent.flight_core import SPEED_FOR_HEADING, Action, CoreConfig, FlightCore, Observed
from agent.modes import AIRBORNE
from comms.schema import Command, CommandKind, Mission, MissionItem, MissionItemKind, Mode

K = MissionItemKind
SIGMAS_M = (0.3, 0.5, 0.55, 0.6, 0.61, 1.0)
"""Below, at and beyond the 0.5 m GNSS note's levels (0.5 m back, 0.6 m poor)."""
BATTERIES_PCT = (100.0, 60.0, 25.0 + 1e-9, 25.0, 12.0, 10.0, 9.0, math.nan)


def _cmd(kind: CommandKind, *params: float, nonce: int) -> Command:
    return Command(kind, nonce, 0, params=(*params, 0.0, 0.0, 0.0)[:3])


def _mission(rng) -> Mission:
    """Waypoints inside a 60 m fence, a wait, and an ending."""
    items = [
        MissionItem(
            K.WAYPOINT,
            x=float(rng.uniform(-30, 30)),
            y=float(rng.uniform(-30, 30)),
            alt_m=float(rng.uniform(3, 15)),
            hold_s=float(rng.choice([0.0, 0.5])),
        )
        for _ in range(int(rng.integers(1, 4)))
    ]
    items.insert(int(rng.integers(0, len(items) + 1)), MissionItem(K.HOLD, hold_s=0.4))
    items.append(MissionItem(K(int(rng.choice([K.LAND, K.RETURN, K.HOLD])))))
    return Mission(1, 1, tuple(items))


def _telemetry(rng, core: FlightCore, relay: bool) -> Observed:
    """Mostly what the mode flies (in the air while airborne), near what would make an event
    (the goal, the take-off altitude, the ground, the fence's edge, the heading's speed
    threshold) as often as far from it; now and then a vehicle on the ground in the air."""
    fence_m = core.cfg.failsafe.geofence_radius_m
    target = core.targets()[0]
    mode = core.mode_of(0)
    airborne = (mode in AIRBORNE) == (rng.random() < (0.7 if mode is Mode.LANDING else 0.99))
    where = int(rng.integers(5))
    if where == 0 and not math.isnan(target[0]):
        pos = target + rng.normal(0.0, 0.8, 3) * rng.choice([0.1, 1.0, 3.0])
    elif where == 1:
        pos = np.array([*rng.uniform(-20, 20, 2), -core.takeoff_alt_m[0] + rng.normal(0, 0.4)])
    elif where == 2 and fence_m:
        edge = fence_m * float(rng.choice([1 - 1e-3, 1.0, 1 + 1e-3]))
        pos = np.array([edge, 0.0, -8.0]) if rng.random() < 0.5 else np.array([0.0, -edge, -8.0])
    else:
        pos = np.array([*rng.uniform(-50, 50, 2), rng.uniform(-30, -1)])
    if not airborne:
        pos[2] = 0.0
    above_m_s = SPEED_FOR_HEADING * core.cfg.guidance.cruise_speed_m_s
    speed = rng.uniform(0, 3)
    if rng.random() < 0.15:
        speed = rng.choice([0.0, above_m_s, above_m_s * (1 + 1e-12)])
    ang = rng.uniform(-math.pi, math.pi)
    vel = np.array([speed * math.cos(ang), speed * math.sin(ang), rng.normal(0, 0.3)])
    if speed == above_m_s and rng.random() < 0.5:
        vel[:2] = (above_m_s, 0.0)  # exactly on it
    armed = airborne if rng.random() < 0.9 else not airborne
    in_air = airborne if rng.random() < 0.9 else not airborne
    sigma = None if rng.random() < 0.3 else np.array([rng.choice(SIGMAS_M)])
    sep = None if not relay or rng.random() < 0.3 else np.array([rng.choice([np.nan, 3.0, 4.5])])
    return Observed(
        pos[None],
        vel[None],
        np.array([armed]),
        np.array([in_air]),
        np.array([rng.choice(BATTERIES_PCT) if rng.random() < 0.05 else 80.0]),
        np.array([rng.random() < 0.9]),
        sigma,
        sep,
    )


_KINDS, _WEIGHTS = zip(
    *[
        (CommandKind.TAKEOFF, 3),
        (CommandKind.GOTO_LOCAL, 4),
        (CommandKind.HOLD, 1),
        (CommandKind.LAND, 1),
        (CommandKind.RETURN, 1),
        (CommandKind.MISSION_START, 2),
        (CommandKind.MISSION_PAUSE, 1),
        (CommandKind.MISSION_RESUME, 1),
        (CommandKind.MISSION_ABORT, 1),
        (CommandKind.MISSION_STATUS, 2),  # a mission upload instead
    ],
    strict=True,
)
_KIND_P = np.array(_WEIGHTS) / sum(_WEIGHTS)


def _command(rng, core: FlightCore, nonce: int) -> Command | Mission:
    """Any command but a kill, or a mission upload."""
    fence_m = core.cfg.failsafe.geofence_radius_m or 60.0
    kind = CommandKind(int(rng.choice(_KINDS, p=_KIND_P)))
    if kind is CommandKind.TAKEOFF:
        return _cmd(kind, float(rng.uniform(2, 20)), nonce=nonce)
    if kind is CommandKind.GOTO_LOCAL:  # inside the fence and outside it
        n, e = rng.uniform(-1.2, 1.2, 2) * fence_m
        return _cmd(kind, n, e, -rng.uniform(2, 20), nonce=nonce)
    if kind is CommandKind.MISSION_STATUS:
        return _mission(rng)
    return _cmd(kind, nonce=nonce)


def _inner(fs: Failsafes) -> tuple:
    return (fs._gcs_seen_s, fs._gcs_failsafe, fs._battery_acted, fs._fence_tripped, fs.flags)


def _same_actions(a: list[Action] | tuple[Action, ...], b, what: str) -> None:
    assert list(a) == list(b), what
    for x, y in zip(a, b, strict=True):
        if x.undo is None or y.undo is None:
            assert x.undo is None and y.undo is None, what
            continue
        assert x.undo.mode is y.undo.mode, what
        for name in ("goal_m", "hold_m", "resume_goal_m"):
            np.testing.assert_array_equal(getattr(x.undo, name), getattr(y.undo, name), what)


def _same(one: FlightCore, ref: FlightCore, what: str) -> None:
    for name in (
        "mode",
        "epoch",
        "gnss_poor",
        "mission_waiting",
        "goal_m",
        "hold_m",
        "home_m",
        "resume_goal_m",
        "takeoff_alt_m",
        "battery_pct",
        "pos_sigma_m",
    ):
        np.testing.assert_array_equal(getattr(one, name), getattr(ref, name), err_msg=what)
    # math.atan2 and numpy's arctan2 (SIMD) may round a last bit apart
    np.testing.assert_allclose(one.heading_rad, ref.heading_rad, rtol=0, atol=1e-12, err_msg=what)
    np.testing.assert_array_equal(one.targets(), ref.targets(), err_msg=what)
    assert (one.now_s, one.onboard_separation_m) == (ref.now_s, ref.onboard_separation_m), what
    assert _inner(one.failsafes[0]) == _inner(ref.failsafes[0]), what
    assert one.drain_notes() == ref.drain_notes(), what
    runs = [(r.describe(), r.progress()) if r else None for r in (one.missions[0], ref.missions[0])]
    assert runs[0] == runs[1], what
    np.testing.assert_array_equal(one.returns.phase, ref.returns.phase, err_msg=what)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("relay", [False, True])
@pytest.mark.parametrize("fence_m", [0.0, 60.0])
def test_one_row_tick_in_floats_equals_the_rows_in_arrays(
    seed: int, relay: bool, fence_m: float
) -> None:
    """Random telemetry, commands, failed actions and station losses: after every tick the
    one-row core (`observe`, which takes quiet ticks in floats) and the reference (always
    `_observe_rows`) agree on everything, and both paths were taken many times."""
    rng = np.random.default_rng(seed)
    cfg = CoreConfig(failsafe=FailsafeConfig(geofence_radius_m=fence_m))
    one = FlightCore(cfg, 1, now_s=0.0, velocity_mode=not relay)
    ref = FlightCore(cfg, 1, now_s=0.0, velocity_mode=not relay)
    taken = []
    observe_one = one._observe_one

    def counted(*args) -> bool:
        taken.append(observe_one(*args))
        return taken[-1]

    one._observe_one = counted  # type: ignore[method-assign]
    now_s, gcs_alive, pos_m = 0.0, True, None
    for tick in range(1500):
        what = f"seed {seed} tick {tick}"
        if rng.random() < 0.15 or tick == 1400:
            # a kill ends the flight for good: the last hundred ticks
            cmd = _command(rng, one, tick) if tick != 1400 else _cmd(CommandKind.KILL, nonce=tick)
            link_ok = bool(rng.random() < 0.95)
            if isinstance(cmd, Mission):
                a, b = one.load_mission(0, cmd), ref.load_mission(0, cmd)
            else:
                a, b = one.command(0, cmd, pos_m, link_ok), ref.command(0, cmd, pos_m, link_ok)
            assert a == b, what
            _same_actions(a.actions, b.actions, what)
            _same(one, ref, what)
        if rng.random() < (0.02 if gcs_alive else 0.1):
            gcs_alive = not gcs_alive
        now_s += 0.1 if rng.random() < 0.9 else float(rng.choice([2.0, 6.0]))
        obs = _telemetry(rng, one, relay)
        pos_m = obs.pos_m[0]
        acts = one.observe(now_s, obs, gcs_alive)
        _same_actions(acts, ref._observe_rows(now_s, obs, gcs_alive), what)
        for act in acts:
            if rng.random() < 0.2:  # the autopilot refuses: both roll back alike
                assert one.action_failed(act, "denied") == ref.action_failed(act, "denied")
        _same(one, ref, what)
        np.testing.assert_array_equal(
            one.guided_rows(obs.armed, obs.link_ok), ref._guided_rows(obs.armed, obs.link_ok)
        )
    assert taken.count(True) > 500 and taken.count(False) > 400, (
        taken.count(True),
        taken.count(False),
    )


@pytest.mark.parametrize("seed", range(4))
def test_guided_rows_of_one_equals_the_rows(seed: int) -> None:
    """Every mode, with and without a target, armed or not, link up or down: one row's answer
    in Python bools is the rows' answer, a read-only row-index array."""
    rng = np.random.default_rng(seed)
    core = FlightCore(CoreConfig(), 1, now_s=0.0)
    relay = FlightCore(CoreConfig(), 1, now_s=0.0, velocity_mode=False)
    for _ in range(400):
        c = core if rng.random() < 0.8 else relay
        c.mode[0] = int(rng.choice([m.value for m in Mode]))
        c.goal_m[0] = np.nan if rng.random() < 0.3 else rng.normal(0, 10, 3)
        c.hold_m[0] = np.nan if rng.random() < 0.3 else rng.normal(0, 10, 3)
        armed, link_ok = np.array([rng.random() < 0.7]), np.array([rng.random() < 0.8])
        got, want = c.guided_rows(armed, link_ok), c._guided_rows(armed, link_ok)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == want.dtype == np.intp and not got.flags.writeable


@pytest.mark.parametrize("fence_m", [0.0, 40.0])
def test_calm_one_equals_calm_rows(fence_m: float) -> None:
    """The failsafe's calm test for one vehicle in floats is `calm_rows`' answer, but for
    positions within FENCE_TIE_M inside the fence's edge, where it says not calm (the safe
    answer: `evaluate` runs)."""
    rng = np.random.default_rng(7)
    cfg = FailsafeConfig(geofence_radius_m=fence_m)
    n = 2000
    battery = rng.choice(BATTERIES_PCT, n)
    pos = rng.normal(0.0, 30.0, (n, 3))
    pos[: n // 10, 0] = rng.choice([np.nan, np.inf, fence_m, fence_m * (1 + 1e-3)], n // 10)
    pos[: n // 10, 1] = 0.0
    edges, calm = 0, 0
    for gcs_alive in (True, False):
        rows = cfg.calm_rows(gcs_alive, battery, pos).tolist()
        calm += sum(rows)
        for i in range(n):
            one = cfg.calm_one(gcs_alive, float(battery[i]), float(pos[i, 0]), float(pos[i, 1]))
            on_edge = fence_m and abs(math.hypot(*pos[i, :2]) - fence_m) <= FENCE_TIE_M
            edges += bool(on_edge and rows[i])
            assert one == (rows[i] and not on_edge), (gcs_alive, battery[i], pos[i])
    assert calm > n // 10  # both answers were tried
    assert edges > 0 or not fence_m  # the edge was tried
