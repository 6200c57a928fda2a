"""The runtime's fast paths equal their plain references.

- Network.lstm_last (float32, 7 numpy calls a step, all inputs projected at once) =
  lstm_last_reference (float64, one step at a time) within 1e-5, and Network.forward_one (the
  LSTM and the head on per-thread buffers) = head_forward of the reference within 1e-5;
- features.observe_fast = features.observe within 1e-12 (and the same neighbours);
- safety.filter_one = safety.filter_velocity within 1e-12;
- GuidancePolicy.command = the reference pipeline within 1e-5; its checks still name the input.
"""

from __future__ import annotations

import numpy as np
import pytest

from firmware import safety_cases as sc
from policy import features, safety
from policy.runtime import GuidancePolicy

TOL = 1e-5


@pytest.fixture(scope="module")
def pol():
    return GuidancePolicy.load()


def _scene(rng, k, spread=25.0):
    return rng.uniform(-spread, spread, (k, 2)), rng.uniform(-10, 10, k)


def test_lstm_fast_equals_reference(pol):
    rng = np.random.default_rng(0)
    worst = 0.0
    for n in (0, 1, 2, 7, 19, 40):
        for _ in range(10):
            seq = rng.normal(0, 1.0, (n, pol.obs_cfg.input_size))
            a, b = pol.net.lstm_last(seq), pol.net.lstm_last_reference(seq)
            assert a.shape == b.shape == (pol.net.hidden,)
            worst = max(worst, float(np.abs(a - b).max()))
    assert worst <= TOL, worst


def test_forward_one_equals_the_reference_network(pol):
    rng = np.random.default_rng(5)
    worst = 0.0
    for n in (0, 1, 2, 7, 19, 40, 70):  # 70: the buffers grow past their first size
        for _ in range(10):
            seq = rng.normal(0, 1.0, (n, pol.obs_cfg.input_size))
            goal = rng.normal(0, 1.0, 2)
            ref = pol.net.head_forward(pol.net.lstm_last_reference(seq), goal)
            worst = max(worst, float(np.abs(np.array(pol.net.forward_one(seq, goal)) - ref).max()))
    assert worst <= TOL, worst


def test_command_from_many_threads_equals_one_thread(pol):
    """The fast path's buffers are per thread: vehicles of one process may share a policy."""
    import threading

    rng = np.random.default_rng(6)
    scenes = []
    for k in (0, 3, 19, 45):
        nbr, hdg = _scene(rng, k, 15.0)
        scenes.append(
            (rng.uniform(-3, 3, 2), np.zeros(2), 0.2, [30.0, 5.0], nbr, np.zeros((k, 2)), hdg)
        )
    want = [pol.command(*s) for s in scenes]
    bad = []

    def worker(i):
        for _ in range(200):
            got = pol.command(*scenes[i])
            if not np.array_equal(got, want[i]):
                bad.append((i, got))

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(len(scenes))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not bad, bad[:3]


@pytest.mark.parametrize(
    "cfg",
    [
        features.ObsConfig("sincos", "closest_last", 10.0, 20.0),
        features.ObsConfig("sincos", "index", 1.0, 0.0),
        features.ObsConfig("paper", "closest_last", 1.0, 8.0),
    ],
    ids=["shipped", "sincos-index", "paper"],
)
def test_observe_fast_equals_observe(cfg):
    rng = np.random.default_rng(1)
    for k in (0, 1, 3, 19, 45):
        for max_n in (None, 10):
            for _ in range(10):
                nbr, hdg = _scene(rng, k)
                if k > 2:
                    nbr[1] = nbr[2]  # equal distances: the stable order must match
                own, h, goal = rng.uniform(-5, 5, 2), float(rng.uniform(-10, 10)), [40.0, -7.0]
                ref = features.observe(own, h, goal, nbr, hdg, cfg, max_n)
                fast = features.observe_fast(own, h, goal, nbr, hdg, cfg, max_n)
                np.testing.assert_array_equal(fast[2], ref[2])
                np.testing.assert_allclose(fast[0], ref[0], atol=1e-12, rtol=0)
                np.testing.assert_allclose(fast[1], ref[1], atol=1e-12, rtol=0)
    # a neighbour exactly on top (no bearing): the fallback, same as the reference
    nbr = np.array([[1.0, 2.0], [5.0, 5.0]])
    ref = features.observe([1.0, 2.0], 0.3, [9, 9], nbr, [0.1, 0.2], cfg)
    fast = features.observe_fast(np.array([1.0, 2.0]), 0.3, [9, 9], nbr, [0.1, 0.2], cfg)
    np.testing.assert_allclose(fast[0], ref[0], atol=1e-12)


def test_filter_one_equals_filter_velocity():
    rng = np.random.default_rng(2)
    moved = 0
    for _ in range(1500):
        c = sc.random_case(rng, scale=float(rng.choice([0.5, 1.0, 3.0])))
        cfg = safety.SafetyConfig(*c.cfg)
        nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
        own, pref = np.array(c.own), np.array(c.pref)
        ref = safety.filter_velocity(own[:2], own[2:], pref, nb[:, :2], nb[:, 2:], cfg)
        fast = safety.filter_one(own[:2], own[2:], pref, nb[:, :2], nb[:, 2:], cfg)
        np.testing.assert_allclose(fast, ref, atol=1e-12, rtol=0)
        moved += not np.allclose(ref, pref)
    assert moved > 500


def test_command_equals_the_reference_pipeline(pol):
    rng = np.random.default_rng(3)
    s = pol.dist_scale_m
    worst = 0.0
    for k in (0, 1, 5, 19, 30):
        for _ in range(15):
            nbr, hdg = _scene(rng, k, 12.0)
            nv = rng.normal(0, 0.7, (k, 2))
            own, vel, h, goal = (
                rng.uniform(-3, 3, 2),
                rng.normal(0, 0.5, 2),
                0.4,
                rng.uniform(-30, 30, 2),
            )
            v = pol.command(own, vel, h, goal, nbr, nv, hdg)
            a = pol.action_reference(own / s, h, goal / s, nbr / s, hdg)
            ref = features.action_to_velocity(a, h) * pol.cruise_speed_m_s
            if k:
                ref = safety.filter_velocity(own, vel, ref, nbr, nv, pol.safety_cfg)
            worst = max(worst, float(np.abs(v - ref).max()))
    assert worst <= TOL, worst


def test_command_checks_still_name_the_bad_input(pol):
    ok = dict(
        pos_m=np.zeros(2),
        vel_m_s=np.zeros(2),
        heading_rad=0.0,
        goal_m=np.ones(2),
        nbr_pos_m=np.ones((2, 2)),
        nbr_vel_m_s=np.zeros((2, 2)),
        nbr_heading_rad=np.zeros(2),
    )
    for name in ok:
        bad = dict(ok)
        bad[name] = np.full_like(np.asarray(ok[name], dtype=float), np.nan)
        with pytest.raises(ValueError, match=f"{name} must be finite"):
            pol.command(**bad)
    with pytest.raises(ValueError, match="nbr_vel_m_s must have shape"):
        pol.command(**{**ok, "nbr_vel_m_s": np.zeros((3, 2))})
