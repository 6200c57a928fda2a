"""The runtime's fast paths equal their plain references.

- Network.lstm_last (float32, 7 numpy calls a step, all inputs projected at once) =
  lstm_last_reference (float64, one step at a time) within 1e-5, and Network.forward_one (the
  LSTM and the head on per-thread buffers) = head_forward of the reference within 1e-5;
- features.observe_fast = features.observe within 1e-12 (and the same neighbours);
- safety.filter_one = safety.filter_velocity within 1e-12;
- features.closest_last_rows (complex rows for their own projection) = features.observe within
  float32 rounding (and the same neighbours); Actor.action = action_reference within 1e-5;
- GuidancePolicy.command (its fast path in metres and its checked path) = the reference pipeline
  within 1e-5; its checks still name the input, a bad value anywhere included.
"""

from __future__ import annotations

import numpy as np
import pytest

from firmware import safety_cases as sc
from policy import features, safety, sparse
from policy.observation import Observation
from policy.runtime import GuidancePolicy

TOL = 1e-5


@pytest.fixture(scope="module")
def pol():
    return (
        GuidancePolicy.load()
    )  # as the agents fly: the weights' told share, the sparse rule, the filter


def _reference(pol, own, vel, h, goal, nbr, nv, hdg) -> np.ndarray:
    """The plain pipeline: the reference network, then (when on) the padded sparse rule, then
    (with neighbours) the filter."""
    a = pol.actor.action_reference(Observation.at_rest(own, h, goal, nbr, hdg))
    ref = features.action_to_velocity(a, h) * pol.cruise_speed_m_s
    if pol.sparse_rule is not None:
        one = (x[None] for x in (own, vel, np.asarray(goal, float), ref, nbr, nv))
        ref = sparse.choose_padded(
            *one,
            np.ones((1, len(nbr)), bool),
            pol.safety_cfg,
            pol.sparse_rule,
            pol.decision_period_s,
        )[0][0]
    if pol.safety_filter and len(nbr):
        ref = safety.filter_velocity(own, vel, ref, nbr, nv, pol.safety_cfg)
    return ref


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
            ref = _reference(pol, own, vel, h, goal, nbr, nv, hdg)
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


def _rows_scene(rng, k, spread=25.0):
    nbr, hdg = _scene(rng, k, spread)
    if k > 2:
        nbr[1] = nbr[2]  # equal distances: the stable order must match
    return rng.uniform(-5, 5, 2), float(rng.uniform(-10, 10)), nbr, hdg


@pytest.mark.parametrize("sense", [20.0, 8.0, 0.0])
def test_closest_last_rows_equal_observe(sense):
    cfg = features.ObsConfig("sincos", "closest_last", 10.0, sense)
    rng = np.random.default_rng(11)
    scratch = features.RowsTable(64)
    for k in (0, 1, 3, 19, 45, 60):
        for _ in range(10):
            own, h, nbr, hdg = _rows_scene(rng, k)
            ref_seq, _, ref_idx = features.observe(own, h, [40.0, -7.0], nbr, hdg, cfg)
            rows, idx = features.closest_last_rows(nbr - own, h, hdg, sense, scratch)
            np.testing.assert_array_equal(idx, ref_idx)
            assert rows.dtype == np.complex64 and rows.shape == (len(ref_idx), 3)
            seq = features.rows_as_seq(rows, cfg.dist_scale)
            np.testing.assert_allclose(seq, ref_seq, atol=2e-6, rtol=1e-6)
            np.testing.assert_array_equal(rows[:, 0].imag, 1.0)


def test_closest_last_rows_refuse_what_observe_must_do():
    scratch = features.RowsTable(8)
    nbr, hdg = np.array([[1.0, 2.0], [5.0, 5.0]]), np.zeros(2)
    for bad in ([1.0, 2.0], [np.nan, 0.0], [np.inf, 0.0]):
        rel = nbr.copy()
        rel[0] = bad
        assert features.closest_last_rows(rel - [1.0, 2.0], 0.3, hdg, 20.0, scratch) is None


@pytest.mark.parametrize("max_n", [None, 10, 25])
def test_action_equals_action_reference(max_n):
    """`action`'s fast path (closest_last_rows + forward_rows) and, beyond max_neighbours, its
    general path, against the float64 reference."""
    pol = GuidancePolicy.load(max_neighbours=max_n)
    s = pol.dist_scale_m
    rng = np.random.default_rng(12)
    worst = 0.0
    for k in (0, 1, 2, 19, 60):
        for _ in range(8):
            own, h, nbr, hdg = _rows_scene(rng, k, 15.0)
            goal = rng.uniform(-40, 40, 2)
            obs = Observation.at_rest(own * s, h, goal * s, nbr * s, hdg)
            a = pol.actor.action(obs)
            ref = pol.actor.action_reference(obs)
            assert a.shape == (2,)
            worst = max(worst, float(np.abs(a - ref).max()))
    # a neighbour exactly on top: the general path, as the reference
    nbr = np.array([[1.0, 2.0], [5.0, 5.0]])
    obs = Observation.at_rest(
        np.array([1.0, 2.0]) * s, 0.3, [9.0 * s, 9.0 * s], nbr * s, [0.1, 0.2]
    )
    a = pol.actor.action(obs)
    ref = pol.actor.action_reference(obs)
    worst = max(worst, float(np.abs(a - ref).max()))
    assert worst <= TOL, worst


@pytest.mark.parametrize("filt", [False, True])
@pytest.mark.parametrize("policy_sep", [None, 1.25])
def test_command_fast_path_equals_checked_path_and_reference(filt, policy_sep):
    """The fast path (metres, no scaling), the checked path (scaled to policy units) and the
    plain reference agree, for 0-60 neighbours, views of wider arrays (as the agents pass),
    a list goal and a numpy heading."""
    pol = GuidancePolicy.load(safety_filter=filt, policy_separation_m=policy_sep)
    rng = np.random.default_rng(13)
    worst = 0.0
    for k in (0, 1, 5, 19, 60):
        for trial in range(6):
            wide = rng.uniform(-14, 14, (k, 3))
            nbr = wide[:, :2]  # not contiguous
            nv, hdg = rng.normal(0, 0.7, (k, 2)), rng.uniform(-4, 4, k)
            own, vel = rng.uniform(-3, 3, 2), rng.normal(0, 0.5, 2)
            h = np.float64(rng.uniform(-4, 4)) if trial % 2 else float(rng.uniform(-4, 4))
            goal = rng.uniform(-30, 30, 2)
            goal_in = [float(goal[0]), float(goal[1])] if trial % 3 == 0 else goal
            fast = Observation._fast(own, vel, h, goal_in, nbr, nv, hdg)
            assert fast is not None and pol.actor._action_rows(fast) is not None
            v = pol.command(own, vel, h, goal_in, nbr, nv, hdg)
            conv = Observation._converted(own, vel, h, goal_in, nbr, nv, hdg)
            v_checked = pol._velocity(pol.actor._action_seq(conv), conv, True)
            ref = _reference(pol, own, vel, h, goal, nbr, nv, hdg)
            assert v.shape == (2,) and v.dtype == np.float64
            worst = max(worst, float(np.abs(v - ref).max()), float(np.abs(v_checked - ref).max()))
    assert worst <= TOL, worst


def test_command_finds_one_bad_value_anywhere(pol):
    """A single non-finite entry among finite ones, in arrays the fast path takes, still gets
    the checked path's named error; a finite input whose x.x overflows is still served."""
    k = 3
    ok = dict(
        pos_m=np.zeros(2),
        vel_m_s=np.zeros(2),
        heading_rad=0.1,
        goal_m=np.array([10.0, 0.0]),
        nbr_pos_m=np.array([[4.0, 1.0], [-3.0, 2.0], [0.5, -6.0]]),
        nbr_vel_m_s=np.zeros((k, 2)),
        nbr_heading_rad=np.zeros(k),
    )
    assert Observation._fast(**ok) is not None
    for name, value in ok.items():
        for bad in (np.nan, np.inf, -np.inf):
            args = dict(ok)
            if isinstance(value, float):
                args[name] = bad
            else:
                arr = value.copy()
                arr.reshape(-1)[-1] = bad
                args[name] = arr
            with pytest.raises(ValueError, match=f"{name} must be finite"):
                pol.command(**args)
    huge = dict(ok, nbr_vel_m_s=np.full((k, 2), 1e200))
    assert np.isfinite(pol.command(**huge)).all()
