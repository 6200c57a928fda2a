"""GNSS worse than the preset: the policy is told a berth that grows with the filter's inflation
of the excess (policy.runtime.told_scale, covey_guidance.c covey_told_scale). The zoomed view
is exactly a policy told that berth; numpy and C agree; at or below 0.5 m nothing changes."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from policy.observation import Observation, Observations, Sky
from policy.runtime import TOLD_SIGMA_FREE_M, GuidancePolicy, told_scale

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def test_told_scale_values():
    assert told_scale(3.0, 4.0, 0.5, 0.5, 0.5) == 1.0
    assert told_scale(3.0, 4.0, 0.5, 0.2, 0.0) == 1.0
    assert told_scale(3.0, 4.0, None, 2.0, 2.0) == 1.0
    # both 1 m: sigma_k sqrt(2) x 0.5 m more than the preset's berth, per 3 m
    assert told_scale(3.0, 4.0, 0.5, 1.0, 1.0) == pytest.approx(1 + 4 * math.sqrt(2) * 0.5 / 3)
    # a poor neighbour alone counts
    assert told_scale(3.0, 4.0, 0.5, 0.0, 1.5) == pytest.approx(1 + 4 * 1.0 / 3)
    # NaN counts as nothing here (the filter refuses it)
    assert told_scale(3.0, 4.0, 0.5, math.nan, math.nan) == 1.0
    rows = told_scale(3.0, 4.0, 0.5, np.array([0.3, 1.0]), np.array([0.0, 1.0]))
    assert rows.shape == (2,) and rows[0] == 1.0 and rows[1] > 1.9


def _scene(rng, k):
    pos = rng.uniform(-10, 10, 2)
    return (
        pos,
        rng.uniform(-1, 1, 2),
        float(rng.uniform(-3, 3)),
        rng.uniform(-30, 30, 2),
        pos + rng.uniform(-12, 12, (k, 2)),
        rng.uniform(-1, 1, (k, 2)),
        rng.uniform(-3, 3, k),
    )


def test_zoomed_view_is_the_policy_told_the_wider_berth():
    """A policy at sigma beyond 0.5 m decides as one built with its told separation times
    told_scale and no grading: the same network, a larger distance scale."""
    graded = GuidancePolicy.load(safety_filter=False, sparse_rule=False)
    told_m = 3 * graded.dist_scale_m
    rng = np.random.default_rng(351)
    grown = 0
    for _ in range(120):
        k = int(rng.integers(0, 8))
        args = _scene(rng, k)
        own, nbr = float(rng.uniform(0, 1.5)), rng.uniform(0, 1.5, k)
        scale = float(told_scale(3.0, graded.safety_cfg.sigma_k, 0.5, own, nbr.max(initial=0)))
        grown += scale > 1.0
        fixed = GuidancePolicy.load(
            safety_filter=False,
            sparse_rule=False,
            policy_separation_m=told_m * scale,
            told_sigma_free_m=None,
        )
        sky = {"pos_sigma_m": own, "nbr_pos_sigma_m": nbr}
        got, want = graded.command(*args, **sky), fixed.command(*args, **sky)
        assert np.abs(got - want).max() < 1e-5
    assert grown > 60  # most scenes are beyond the preset


def test_batch_path_equals_the_single_path():
    pol = GuidancePolicy.load(safety_filter=False, sparse_rule=False)
    rng = np.random.default_rng(352)
    n, k = 12, 5
    scenes = [_scene(rng, k) for _ in range(n)]
    own = rng.uniform(0, 1.5, n)
    nbr = rng.uniform(0, 1.5, (n, k))
    valid = rng.random((n, k)) > 0.2
    obs = Observations(
        *(np.array([s[i] for s in scenes]) for i in range(7)),
        valid,
        pos_sigma_m=own,
        nbr_pos_sigma_m=nbr,
    )
    batch = pol.command_batch(obs)
    for i, s in enumerate(scenes):
        m = valid[i]
        one = pol.command(
            *s[:4], s[4][m], s[5][m], s[6][m], pos_sigma_m=own[i], nbr_pos_sigma_m=nbr[i, m]
        )
        assert np.abs(batch[i] - one).max() < 1e-5


def test_preset_sigma_and_exact_positions_are_unchanged():
    """At 0.5 m and below (the preset) and with exact positions, nothing is zoomed."""
    graded = GuidancePolicy.load()
    plain = GuidancePolicy.load(told_sigma_free_m=None)
    rng = np.random.default_rng(353)
    for _ in range(30):
        k = int(rng.integers(0, 6))
        args = _scene(rng, k)
        sky = {"pos_sigma_m": float(rng.uniform(0, 0.5)), "nbr_pos_sigma_m": np.full(k, 0.5)}
        assert np.array_equal(graded.command(*args, **sky), plain.command(*args, **sky))
        assert np.array_equal(graded.command(*args), plain.command(*args))
    obs = Observation.shaped(*_scene(rng, 3), Sky(0.3, np.array([0.1, 0.5, 0.0])))
    assert obs.zoomed(1.0) is obs


def test_bad_free_sigma_is_refused():
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="told_sigma_free_m must be finite and >= 0"):
            GuidancePolicy.load(told_sigma_free_m=bad)


def test_traffic_accuracy_does_not_rescale_the_view():
    """An ADS-B report's tens of metres are traffic's: the filter pads its pair, but the
    network's told berth grows only with covey's own vehicles' sigmas."""
    sky = Sky(0.5, np.array([0.5, 30.0, 20.0]), np.array([True, False, True]))
    assert sky.nbr_sigma_max_m() == 20.0
    manned = Sky(0.5, np.array([0.5, 30.0, 20.0]), None, np.array([False, False, True]))
    assert manned.nbr_sigma_max_m() == 30.0
    only_traffic = Sky(0.5, np.array([30.0]), np.array([False]))
    assert only_traffic.nbr_sigma_max_m() == 0.0
    obs = Observations(
        *(np.zeros(s) for s in ((2, 2), (2, 2), (2,), (2, 2), (2, 3, 2), (2, 3, 2), (2, 3))),
        np.array([[True, True, False], [True, True, True]]),
        pos_sigma_m=np.array([0.5, 0.5]),
        nbr_pos_sigma_m=np.array([[0.5, 40.0, 9.0], [0.7, 0.2, 40.0]]),
        nbr_cooperative=np.array([[True, False, True], [True, True, False]]),
    )
    assert obs.nbr_sigma_max_m().tolist() == [0.5, 0.7]  # row 0: the 9 m slot is not valid


@needs_cc
def test_c_told_scale_equals_numpy():
    from firmware.cpolicy import CPolicy

    rng = np.random.default_rng(354)
    for free in (TOLD_SIGMA_FREE_M, 0.0, 1.2, None):
        cpol = CPolicy.load(told_sigma_free_m=free)
        for _ in range(80):
            k = int(rng.integers(0, 6))
            own = float(np.float32(rng.uniform(0, 2)))
            nbr = rng.uniform(0, 2, k).astype(np.float32)
            if k and rng.random() < 0.2:
                nbr[0] = np.nan
            coop = rng.random(k) > 0.3
            manned = rng.random(k) < 0.2
            sky = Sky(own, nbr.astype(float), coop, manned)
            want = told_scale(3.0, cpol.safety_cfg.sigma_k, free, own, sky.nbr_sigma_max_m())
            got = cpol.told_scale(own, nbr, coop, manned)
            assert got == pytest.approx(float(want), rel=1e-6)
    cpol = CPolicy.load()
    # exact neighbours with kinds (no sigmas given): only the own sigma counts
    flags = np.array([True, False])
    assert cpol.told_scale(0.4, None, flags, ~flags) == 1.0
    assert cpol.told_scale(1.0, None, flags) == pytest.approx(1 + 4 * 0.5 / 3, rel=1e-6)
    with pytest.raises(ValueError, match="told_sigma_free_m must be finite and >= 0"):
        CPolicy.load(told_sigma_free_m=-1.0)


@needs_cc
def test_c_decisions_equal_numpy_beyond_the_preset():
    """The C core's decision (CPolicy.preferred) and its onboard tick (covey_guidance_step,
    deciding every tick) equal numpy's with sigmas beyond the preset: the network told the
    same grown berth, then the same sparse rule and filter."""
    from firmware.cpolicy import CPolicy
    from policy import safety

    cpol = CPolicy.load()
    npol = GuidancePolicy.load()
    tick = cpol.onboard(0.0)
    rng = np.random.default_rng(355)
    for t in range(80):
        k = int(rng.integers(1, 7))
        args = _scene(rng, k)
        own = float(np.float32(rng.uniform(0.5, 1.5)))
        nbr = rng.uniform(0.0, 1.5, k).astype(np.float32).astype(float)
        coop = rng.random(k) > 0.2  # some traffic, with sigmas of its own
        sky = {"pos_sigma_m": own, "nbr_pos_sigma_m": nbr, "nbr_cooperative": coop}
        held_c, held_n = cpol.preferred(*args, **sky), npol.preferred(*args, **sky)
        assert np.abs(held_c - held_n).max() < 1e-4
        step = tick.step(Observation.shaped(*args, Sky(own, nbr, coop)), 0.1 * t)
        assert step.status == "ok"
        want = safety.filter_velocity(
            args[0], args[1], held_n, args[4], args[5], npol.safety_cfg, **sky
        )
        assert np.abs(step.vel_m_s - want).max() < 1e-4
