"""The vectorised environment equals the plain per-agent loop; reward constants."""

from dataclasses import replace

import numpy as np
import pytest

from policy.env import EnvConfig, SwarmEnv, cav_reward, reference_step, sample_scenario
from policy.features import ObsConfig


@pytest.mark.parametrize(
    ("w_prog", "ccd", "safety_filter"),
    [(0.0, False, False), (10.0, True, False), (10.0, True, True)],
)
def test_step_matches_reference_loop(w_prog, ccd, safety_filter):
    cfg = EnvConfig(
        num_envs=16,
        max_vehicles=5,
        w_prog=w_prog,
        max_steps=30,
        ccd=ccd,
        safety_filter=safety_filter,
    )
    env = SwarmEnv(cfg, ObsConfig("sincos", "closest_last", 10.0, 20.0))
    env.reset(seed=3)
    rng = np.random.default_rng(4)
    for _ in range(40):
        # push pairs together now and then so that collisions happen
        _step_both(env, rng.normal(0.3, 0.8, (16, 5, 2)), cfg)


def _step_both(env: SwarmEnv, actions, cfg: EnvConfig) -> None:
    """One env.step, checked against reference_step on copies of the state before it (with the
    drifts before and after the step), then the finished arenas reset."""
    before = tuple(
        x.copy() for x in (env.pos, env.goal, env.heading, env.active, env.trip_m, env.t)
    )
    vel, drift = env.vel.copy(), env.drift.copy()
    r, d, info = env.step(actions)
    pos, heading, active, reward, done = reference_step(
        *before, actions, cfg, vel=vel, drift=drift, drift_after=env.drift.copy()
    )
    np.testing.assert_allclose(env.pos, pos, atol=1e-12)
    np.testing.assert_allclose(env.heading, heading, atol=1e-12)
    np.testing.assert_array_equal(env.active, active)
    np.testing.assert_allclose(r, reward, atol=1e-9)
    np.testing.assert_array_equal(d, done)
    env.reset_envs(info["env_done"])


def test_reset_is_seeded_and_respects_the_arena():
    cfg = EnvConfig(num_envs=200)
    a, b = SwarmEnv(cfg, ObsConfig()), SwarmEnv(cfg, ObsConfig())
    a.reset(seed=7)
    b.reset(seed=7)
    np.testing.assert_array_equal(a.pos, b.pos)
    n = a.active.sum(1)
    assert n.min() >= 1 and n.max() <= 5
    # geometric(1/3) capped at 5: P(1) = 1/3
    assert 0.2 < np.mean(n == 1) < 0.47
    for e in range(cfg.num_envs):
        k = n[e]
        s, g = a.pos[e, :k], a.goal[e, :k]
        assert np.all((s >= 0) & (s <= 60) & (g >= 0) & (g <= 60))
        assert np.all(np.hypot(*(g - s).T) >= 10)
        for i in range(k):
            for j in range(i):
                assert np.hypot(*(s[i] - s[j])) >= 10 and np.hypot(*(g[i] - g[j])) >= 10
        np.testing.assert_allclose(a.heading[e, :k], np.arctan2((g - s)[:, 1], (g - s)[:, 0]))


def test_cav_reward_shape():
    cfg = EnvConfig()
    assert cav_reward(12.0, cfg) == 0.0
    assert cav_reward(10.0, cfg) == 0.0
    assert cav_reward(8.0, cfg) == pytest.approx(-1.0)
    assert cav_reward(6.0, cfg) == pytest.approx(-2.0)
    assert cav_reward(3.0, cfg) == pytest.approx(-1000.0)
    assert cav_reward(1.0, cfg) == -1000.0
    assert -1000 < cav_reward(4.5, cfg) < -2


def test_arrival_and_collision_leave_the_scene():
    cfg = EnvConfig(num_envs=1, max_vehicles=3)
    env = SwarmEnv(cfg, ObsConfig())
    env.reset(seed=0)
    env.pos[0] = [[0, 0], [0, 2.5], [20, 20]]
    env.goal[0] = [[30, 0], [30, 2.5], [20.5, 20]]
    env.heading[0] = 0.0
    env.active[0] = True
    env.trip_m[0] = [30, 30, 0.5]
    r, d, info = env.step(np.array([[[1, 0], [1, 0], [0.5, 0]]]))
    assert info["collided"][0].tolist() == [True, True, False]
    assert info["arrived"][0].tolist() == [False, False, True]
    assert d[0].all() and info["env_done"][0]
    assert r[0, 2] == pytest.approx(1000 - 1.5 * 100 / 0.5)


@pytest.mark.parametrize("ccd", [False, True])
def test_ccd_catches_a_pass_between_steps(ccd):
    """Both ends of the step are 3.07 m apart, the closest approach is 2.9 m."""
    cfg = EnvConfig(num_envs=1, max_vehicles=2, ccd=ccd)
    env = SwarmEnv(cfg, ObsConfig())
    env.reset(seed=0)
    env.pos[0] = [[0.0, 0.0], [-1.0, 2.9]]
    env.goal[0] = [[-30.0, 0.0], [30.0, 2.9]]
    env.heading[0] = [np.pi, 0.0]
    env.active[0] = True
    _, _, info = env.step(np.array([[[1.0, 0.0], [1.0, 0.0]]]))
    assert np.hypot(*(env.pos[0, 0] - env.pos[0, 1])) > 3.0
    assert info["collided"][0].all() == ccd


def _fly_head_on(cfg: EnvConfig):
    """Two vehicles flying straight at each other's start: (closest, collided, arrived)."""
    env = SwarmEnv(cfg, ObsConfig())
    env.reset(seed=0)
    env.pos[0] = [[0.0, 0.0], [20.0, 0.2]]
    env.goal[0] = [[20.0, 0.0], [0.0, 0.2]]
    env.heading[0] = [0.0, np.pi]
    env.active[0] = True
    env.trip_m[0] = 20.0
    closest, collided, arrived = np.inf, False, np.zeros(2, bool)
    for _ in range(60):
        if not env.active[0].any():
            break
        gd = env.goal[0] - env.pos[0]
        bearing = np.arctan2(gd[:, 1], gd[:, 0]) - env.heading[0]
        both = env.active[0].all()
        _, _, info = env.step(np.stack([np.cos(bearing), np.sin(bearing)], -1)[None])
        if both:
            closest = min(closest, float(np.hypot(*(env.pos[0, 0] - env.pos[0, 1]))))
        collided |= bool(info["collided"][0].any())
        arrived |= info["arrived"][0]
    return closest, collided, arrived


@pytest.mark.parametrize("safety_filter", [False, True])
def test_filter_in_the_loop_keeps_a_head_on_pair_apart(safety_filter):
    """Two vehicles flying straight at each other: they collide unless the environment flies
    their commands through the separation filter, which keeps them 3 m apart and still lets
    both arrive."""
    cfg = EnvConfig(num_envs=1, max_vehicles=2, ccd=True, safety_filter=safety_filter)
    closest, collided, arrived = _fly_head_on(cfg)
    assert collided != safety_filter
    if safety_filter:
        assert closest >= 3.0
        assert arrived.all()


def test_filter_margin_in_the_loop_is_the_given_one():
    """--filter-margin reaches the environment's filter: the pair keeps about
    3 m x (1 + margin), and a bad margin is refused."""
    for margin in (0.1, 0.5):
        cfg = EnvConfig(num_envs=1, max_vehicles=2, ccd=True, safety_filter=True)
        closest, collided, arrived = _fly_head_on(replace(cfg, filter_margin=margin))
        assert not collided and arrived.all()
        assert 3.0 * (1 + margin) - 0.1 <= closest <= 3.0 * (1 + margin) + 0.6, (margin, closest)
    with pytest.raises(ValueError, match="filter_margin"):
        EnvConfig(filter_margin=-0.1)


def test_sample_scenario_counts():
    s, g = sample_scenario(np.random.default_rng(0), 5, EnvConfig())
    assert s.shape == g.shape == (5, 2)


def test_conflict_arenas_cross_near_the_centre():
    """sample_conflict: starts on one circle 6 m apart, goals 6 m apart near the opposite
    points, so every straight path passes within 4 m of the arena's centre; the environment
    draws that share of its arenas this way."""
    from policy.env import sample_conflict

    cfg = EnvConfig()
    rng = np.random.default_rng(5)
    centre = np.full(2, cfg.arena_m / 2)
    for n in (2, 5, 8):
        s, g = sample_conflict(rng, n, cfg)
        assert s.shape == g.shape == (n, 2)
        r = np.hypot(*(s - centre).T)
        np.testing.assert_allclose(r, r[0], atol=1e-9)
        assert 12.0 <= r[0] <= 28.0
        for pts in (s, g):
            d = np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1)) + np.eye(n) * 99
            assert d.min() >= 6.0 - 1e-9
        seg = g - s
        t = np.clip(((centre - s) * seg).sum(-1) / (seg * seg).sum(-1), 0, 1)
        closest = np.hypot(*(s + t[:, None] * seg - centre).T)
        assert closest.max() <= 4.0
    env = SwarmEnv(EnvConfig(num_envs=200, conflict_share=1.0), ObsConfig())
    env.reset(seed=1)
    counts = env.active.sum(1)
    assert counts.min() >= 2
    plain = SwarmEnv(EnvConfig(num_envs=200), ObsConfig())
    plain.reset(seed=1)
    assert (plain.active.sum(1) == 1).any()  # geometric counts: lone vehicles happen


def test_drifting_estimates_step_matches_reference_loop():
    """With drift_m the environment flies every vehicle on its estimate (the filter, inflated by
    sigma_k x the pair's sigma, the progress and the arrival) and judges collisions on the
    truth: the vectorised step equals the plain loop given the same drifts."""
    cfg = EnvConfig(
        num_envs=12,
        max_vehicles=5,
        w_prog=10.0,
        max_steps=30,
        ccd=True,
        safety_filter=True,
        drift_m=0.5,
        conflict_share=0.5,
    )
    env = SwarmEnv(cfg, ObsConfig("sincos", "closest_last", 10.0, 20.0))
    env.reset(seed=7)
    rng = np.random.default_rng(8)
    moved = 0
    for _ in range(30):
        drift = env.drift.copy()
        _step_both(env, rng.normal(0.3, 0.8, (12, 5, 2)), cfg)
        moved += int((np.abs(env.drift - drift) > 1e-6).any())
    assert moved == 30  # the drift is a process, not a constant


def test_drift_is_the_stated_process_and_off_draws_nothing():
    """The estimates' offsets keep drift_m per axis (stationary from the reset on) and are 0
    without it, where the environment's random stream is what it was (ideal training unchanged)."""
    cfg = EnvConfig(num_envs=64, max_vehicles=5, max_steps=400, drift_m=0.5, drift_corr_s=10.0)
    env = SwarmEnv(cfg, ObsConfig())
    env.reset(seed=1)
    first = env.drift[env.active].std()
    samples = []
    for _ in range(60):
        env.step(np.zeros((64, 5, 2)))  # hover: nobody arrives, the drift runs on
        samples.append(env.drift[env.active])
    assert 0.4 < first < 0.6
    assert 0.4 < np.concatenate(samples).std() < 0.6
    plain, off = SwarmEnv(EnvConfig(), ObsConfig()), SwarmEnv(EnvConfig(drift_m=0.0), ObsConfig())
    plain.reset(seed=2)
    off.reset(seed=2)
    assert not off.drift.any()
    np.testing.assert_array_equal(plain.pos, off.pos)
    assert plain.rng.random() == off.rng.random()


def test_collisions_are_judged_on_the_truth_and_the_network_sees_estimates():
    """Two vehicles whose estimates are 8 m apart but whose true positions are 2 m apart
    collide; the observation is of the estimates, zoomed by told_scale."""
    from policy import features

    cfg = EnvConfig(num_envs=1, max_vehicles=2, drift_m=0.5, told_scale=2.4)
    env = SwarmEnv(cfg, ObsConfig())
    env.reset(seed=0)
    env.pos[0] = [[0.0, 0.0], [2.0, 0.0]]
    env.drift[0] = [[-3.0, 0.0], [3.0, 0.0]]
    env.goal[0] = [[0.0, 30.0], [2.0, 30.0]]
    env.heading[0] = [np.pi / 2, np.pi / 2]
    env.active[0] = True
    seq, lengths, goal_feat = env.observe()
    want = features.observe_batch(
        env.est * 2.4, env.heading, env.goal * 2.4, env.active, env.obs_cfg
    )
    np.testing.assert_allclose(seq, want[0])
    np.testing.assert_allclose(goal_feat, want[2])
    _, _, info = env.step(np.array([[[1.0, 0.0], [1.0, 0.0]]]))
    assert info["collided"][0].all()


@pytest.mark.parametrize(
    ("field", "value"), [("drift_m", -0.1), ("drift_corr_s", 0.0), ("told_scale", float("nan"))]
)
def test_bad_drift_settings_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        EnvConfig(**{field: value})
