"""policy/tracking.py: the tracking compensation takes what the velocity loop does not fly off the
next command, and changes nothing where the loop flies what it is told."""

from __future__ import annotations

import math

import numpy as np
import pytest

from policy import evalsim
from policy.evalsim import PERFECT, EvalSimConfig
from policy.pointmass import VehicleModel, integrate
from policy.tracking import Tracking, TrackingConfig


def fly(
    cfg: TrackingConfig | None,
    wind: np.ndarray,
    want,
    plant_lag_s: float = 0.3,
    plant_accel: float = 2.5,
    dt_s: float = 0.1,
    steps: int = 200,
) -> np.ndarray:
    """Ground velocities (steps, n, 2) of n point masses flying `want(t)` (n, 2) through a loop
    of `plant_lag_s` in a steady `wind` (n, 2), the commands corrected by `cfg` (None: not)."""
    n = wind.shape[0]
    pos, vel = np.zeros((n, 2)), np.zeros((n, 2))
    track = Tracking(cfg, n) if cfg else None
    rows = np.arange(n)
    out = []
    for k in range(steps):
        t = k * dt_s
        ground = vel + wind
        cmd = want(t)
        if track is not None:
            cmd = track.correct(rows, t, cmd, ground)
        integrate(pos, vel, cmd, dt_s, plant_accel, lag_s=plant_lag_s, wind_m_s=wind)
        out.append(vel + wind)
    return np.array(out)


def test_a_simulated_vehicle_without_lag_or_gusts_is_not_corrected():
    """The agent's default simulator (no lag, no gusts, a 4 m/s^2 3-D limit) and ideal eval
    vehicles fly their setpoints: the compensation is off for them, whatever is asked."""
    assert not TrackingConfig.for_model(VehicleModel(max_accel_m_s2=4.0)).enabled
    assert not TrackingConfig.for_model(VehicleModel.ideal(), enabled=True).enabled
    assert TrackingConfig.for_model(VehicleModel.realistic()).enabled
    assert TrackingConfig.for_model(VehicleModel(gust_m_s=0.3)).enabled
    # what the shell and covey eval assume: an autopilot gets the defaults, a lag given wins
    assert TrackingConfig.assumed(None) == TrackingConfig()
    assert TrackingConfig.assumed(None, lag_s=0.5).lag_s == 0.5
    assert not TrackingConfig.assumed(None, enabled=False).enabled
    real = TrackingConfig.assumed(VehicleModel.realistic(), lag_s=0.5)
    assert real.enabled and real.lag_s == 0.5 and real.max_accel_m_s2 == 2.5
    assert not TrackingConfig.assumed(VehicleModel.ideal(), lag_s=0.3).enabled


def test_a_loop_that_flies_the_command_is_left_alone():
    """Ideal vehicles (no lag, no limit, no wind): every command goes out exactly as wanted."""
    rng = np.random.default_rng(3)
    cfg = TrackingConfig(lag_s=0.0, max_accel_m_s2=math.inf)  # on: the maths itself gives 0
    track = Tracking(cfg, 4)
    rows = np.arange(4)
    last = np.zeros((4, 2))
    for k in range(100):
        want = rng.uniform(-1.5, 1.5, (4, 2))
        got = track.correct(rows, 0.1 * k, want, last)  # the ideal loop flew the last one
        np.testing.assert_array_equal(got, want)
        last = got


@pytest.mark.parametrize("plant_lag_s", [0.3, 0.5, 0.1])
def test_steady_wind_is_taken_off_the_command(plant_lag_s):
    """A 0.5 m/s wind the loop does not reject: uncorrected, the ground velocity is off by the
    wind; corrected, within 2 cm of the wanted one after 10 s, with the model's 0.3 s lag
    against loops of 0.1, 0.3 and 0.5 s."""
    wind = np.array([[0.5, 0.0], [0.0, -0.4], [0.3, 0.3]])
    want = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    raw = fly(None, wind, lambda t: want, plant_lag_s)
    fixed = fly(TrackingConfig(), wind, lambda t: want, plant_lag_s)
    np.testing.assert_allclose(raw[-1], want + wind, atol=1e-6)
    assert np.abs(fixed[-1] - want).max() < 0.02
    # and it settles: no oscillation left in the last 5 s
    assert np.abs(fixed[-50:] - want).max() < 0.05


def test_turns_behind_a_slower_loop_do_not_ring():
    """A vehicle turning every 3 s behind a 0.5 s loop modelled as 0.3 s, no wind: the
    correction is small, it never makes the ground velocity worse than uncorrected by more than
    a little, and it dies away when the command is steady."""
    wind = np.zeros((1, 2))

    def want(t):
        a = math.floor(t / 3.0) * 1.7
        return np.array([[math.cos(a), math.sin(a)]])

    raw = fly(None, wind, want, plant_lag_s=0.5, steps=300)
    fixed = fly(TrackingConfig(), wind, want, plant_lag_s=0.5, steps=300)
    ideal = np.array([want(0.1 * k) for k in range(300)])
    err_raw = np.linalg.norm(raw - ideal, axis=2)
    err_fixed = np.linalg.norm(fixed - ideal, axis=2)
    assert err_fixed.mean() <= err_raw.mean() * 1.05
    assert np.linalg.norm(fixed[-1], axis=1).max() < 1.05  # no speed built up


def test_the_correction_is_capped_and_disabled_is_a_pass_through():
    cfg = TrackingConfig(max_correction_m_s=0.3, lag_s=0.0, max_accel_m_s2=math.inf)
    track = Tracking(cfg, 1)
    rows = np.array([0])
    want = np.array([[1.0, 0.0]])
    for k in range(100):  # held back by 2 m/s whatever it is told
        got = track.correct(rows, 0.1 * k, want, np.array([[-1.0, 0.0]]))
    assert math.hypot(*(want - got)[0]) == pytest.approx(0.3)
    off = Tracking(TrackingConfig(enabled=False), 1)
    for k in range(10):
        np.testing.assert_array_equal(off.correct(rows, 0.1 * k, want, [[-1.0, 0.0]]), want)


def test_a_row_starts_afresh_after_a_gap_or_forget():
    cfg = TrackingConfig(lag_s=0.0, max_accel_m_s2=math.inf, max_gap_s=2.0)
    track = Tracking(cfg, 2)
    rows = np.arange(2)
    want = np.array([[1.0, 0.0], [0.0, 1.0]])
    got = want
    for k in range(50):  # the loop flies each command exactly, plus 0.5 m/s of wind
        got = track.correct(rows, 0.1 * k, want, got + 0.5)
    assert np.abs(got - (want - 0.5)).max() < 0.01
    track.forget(np.array([1]))
    got = track.correct(rows, 5.0, want, got + 0.5)
    np.testing.assert_array_equal(got[1], want[1])  # forgotten: as wanted
    assert got[0, 0] < 0.6  # kept
    got = track.correct(rows, 8.0, want, got + 0.5)  # 3 s later: both afresh
    np.testing.assert_array_equal(got, want)
    # a NaN measurement restarts its row rather than poisoning it
    got = track.correct(rows, 8.1, want, np.array([[np.nan, 0.0], [0.0, 1.0]]))
    np.testing.assert_array_equal(got[0], want[0])
    assert np.isfinite(track.error_m_s).all()


@pytest.mark.parametrize(
    "field,value",
    [
        ("lag_s", -0.1),
        ("window_s", 0.0),
        ("max_gap_s", math.nan),
        ("max_accel_m_s2", 0.0),
        ("max_correction_m_s", math.inf),
    ],
)
def test_bad_settings_are_refused_with_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TrackingConfig(**{field: value})


def test_eval_with_gusts_flies_straighter_with_the_compensation():
    """One vehicle flying 60 m through 0.5 m/s gusts behind a 0.5 s loop (evalsim, straight-line
    controller): the compensation brings its path nearer the straight line and its time nearer
    the straight-line time, from the same gusts."""
    model = VehicleModel.named("realistic:gust_m_s=0.5,lag_s=0.5,drift_m=0")
    out = {}
    for on in (False, True):
        cfg = EvalSimConfig(vehicles=model, tracking=TrackingConfig.for_model(model, enabled=on))
        rs = [
            evalsim.run(
                [[0.0, 0.0]],
                [[60.0, 0.0]],
                evalsim.straight_line,
                PERFECT,
                cfg,
                np.random.default_rng(s),
            )
            for s in range(6)
        ]
        out[on] = np.mean([r["path_ratio"] for r in rs])
    assert out[True] < out[False] - 0.01
    assert out[True] < 1.03


@pytest.mark.e2e
def test_the_shell_corrects_its_setpoints_in_gusts():
    """A fleet-sim host (the agents' shell, a real Zenoh router on loopback, injected time), two
    vehicles flying 40 m side by side through 0.5 m/s gusts behind a 0.5 s loop: with the
    compensation their true paths stray less from the straight line than without it, from the
    same gusts; the simulator reports the ground velocity (gust included), as GNSS does."""
    from agent.backends.sim import SimConfig
    from agent.hosts import Fleet
    from agent.shell_config import FleetSimConfig
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import AckResult, Command, CommandKind
    from comms.session import embedded_router, free_tcp_port

    model = VehicleModel.named("realistic:gust_m_s=0.5,lag_s=0.5,drift_m=0")

    def cmd(kind, *params):
        return Command(kind, new_nonce(), 0, params=tuple(params) + (0.0,) * (3 - len(params)))

    def stray(tracking: bool) -> float:
        clock = [0.0]
        cfg = FleetSimConfig(
            vehicles=2,
            first_id=31,
            mesh=embedded_router(free_tcp_port(), fleet="track"),
            spacing_m=12.0,
            sim=SimConfig(vehicle=model),
            tracking=tracking,
        )
        with Mesh(cfg.mesh) as mesh:
            fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0], rng=np.random.default_rng(5))
            sim = fleet.sim
            for i in range(2):
                assert fleet.handle_command(i, cmd(CommandKind.TAKEOFF, 5.0)).result is (
                    AckResult.ACCEPTED
                )
            for _ in range(80):
                clock[0] += 0.1
                fleet.tick(clock[0])
            air = sim.true_pos_m[:, 2] < 0
            got = sim.ground_vel_m_s[air, :2] - sim.vel_m_s[air, :2]
            np.testing.assert_allclose(got, sim.body.gust_m_s[air])
            start = sim.true_pos_m[:, :2].copy()
            for i in range(2):
                goal = start[i] + (40.0, 0.0)
                ack = fleet.handle_command(i, cmd(CommandKind.GOTO_LOCAL, *goal, -5.0))
                assert ack.result is AckResult.ACCEPTED, ack.reason
            worst = 0.0
            for _ in range(300):
                clock[0] += 0.1
                fleet.tick(clock[0])
                worst = max(worst, float(np.abs(sim.true_pos_m[:, 1] - start[:, 1]).max()))
            return worst

    on, off = stray(True), stray(False)
    assert on < 0.7 * off, (on, off)


@pytest.mark.parametrize(
    "cfg",
    [
        TrackingConfig(),
        TrackingConfig(lag_s=0.0, max_accel_m_s2=math.inf),
        TrackingConfig(lag_s=0.0, max_accel_m_s2=2.0, max_correction_m_s=0.2),
        TrackingConfig(lag_s=0.5, window_s=0.3, max_gap_s=0.5),
    ],
)
def test_one_row_on_floats_equals_the_array_path(cfg):
    """The agent's one-vehicle fast path against `correct_rows`, step for step: random wanted
    and measured velocities, calm (0.3 s) and held (1 s) ticks, gaps that restart the row,
    NaN measurements, forgetting."""
    rng = np.random.default_rng(11)
    fast, ref = Tracking(cfg, 3), Tracking(cfg, 3)
    t = 0.0
    for k in range(600):
        t += float(rng.choice([0.1, 0.1, 0.3, 1.0, 3.0]))
        row = int(rng.integers(3))
        want = rng.uniform(-2, 2, (1, 2))
        meas = rng.uniform(-2, 2, (1, 2))
        if k % 37 == 0:
            meas[0, int(rng.integers(2))] = np.nan
        if k % 53 == 0:
            fast.forget(np.array([row]))
            ref.forget(np.array([row]))
        got = fast.correct(np.array([row]), t, want, meas)
        exp = ref.correct_rows(np.array([row]), t, want, meas)
        np.testing.assert_allclose(got, exp, rtol=0, atol=1e-12)
        for a in ("loop_m_s", "error_m_s", "cmd_m_s", "t_s"):
            np.testing.assert_allclose(getattr(fast, a), getattr(ref, a), rtol=0, atol=1e-12)
