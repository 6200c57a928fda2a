"""The separation filter for real vehicles: each pair's distance grows with the position
uncertainty, k sqrt(sigma_i^2 + sigma_j^2), and a non-cooperative neighbour leaves the whole
correction to us (with its own separation). policy/safety.py's three paths agree, and the C
core (covey_safety.c, covey_guidance.c) equals them on shared float32 vectors."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import numpy as np
import pytest

from firmware import safety_cases as sc
from policy import safety
from policy.observation import Observation, Sky

PARITY_TOL = 1e-6
"""Max |C - numpy| per component as a share of max_speed (test_firmware_safety's)."""

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def _sky_case(rng):
    """A random sc.FilterCase with per-neighbour sigmas (0-1.5 m, some 0), own sigma and
    cooperative flags (a quarter not), and a config with sigma_k and a wider non-cooperative
    separation now and then."""
    c = sc.random_case(rng, scale=float(rng.choice([0.5, 1.0, 3.0])))
    k = len(c.nbrs)
    f32 = np.float32
    own_sigma = float(f32(rng.choice([0.0, rng.uniform(0, 1.5)])))
    nbr_sigma = rng.uniform(0, 1.5, k).astype(f32).astype(float)
    nbr_sigma[rng.random(k) < 0.2] = 0.0
    coop = rng.random(k) >= 0.25
    cfg = safety.SafetyConfig(*c.cfg)
    cfg = replace(
        cfg,
        sigma_k=float(f32(rng.uniform(0, 4))),
        non_cooperative_radius_m=None if rng.random() < 0.5 else float(f32(rng.uniform(3, 9))),
    )
    return c, cfg, own_sigma, nbr_sigma, coop


def test_numpy_paths_agree_with_uncertainty_and_traffic():
    rng = np.random.default_rng(35)
    for _ in range(300):
        c, cfg, s_own, s_nbr, coop = _sky_case(rng)
        nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
        own = np.array(c.own, dtype=np.float64)
        args = (own[:2], own[2:], np.array(c.pref), nb[:, :2], nb[:, 2:], cfg)
        sky = {"pos_sigma_m": s_own, "nbr_pos_sigma_m": s_nbr, "nbr_cooperative": coop}
        a = safety.filter_velocity(*args, **sky)
        b = safety.filter_one(*args, **sky)
        # the padded path clips the preference to the speed limit before the LP (as it always
        # did): compare it with the clipped preference
        pref = safety._clip_speed(np.array(c.pref), cfg.max_speed_m_s)
        a_clipped = safety.filter_velocity(*args[:2], pref, *args[3:], **sky)
        p = safety.filter_padded(
            own[None, :2],
            own[None, 2:],
            pref[None],
            nb[None, :, :2],
            nb[None, :, 2:],
            np.ones((1, len(nb)), bool),
            cfg,
            pos_sigma_m=np.array([s_own]),
            nbr_pos_sigma_m=s_nbr[None],
            nbr_cooperative=coop[None],
        )[0]
        assert np.allclose(a, b, atol=1e-12) and np.allclose(a_clipped, p, atol=1e-12)


def test_no_uncertainty_and_all_cooperative_is_todays_filter():
    rng = np.random.default_rng(36)
    for _ in range(100):
        c = sc.random_case(rng)
        cfg = safety.SafetyConfig(*c.cfg)
        nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
        own = np.array(c.own, dtype=np.float64)
        args = (own[:2], own[2:], np.array(c.pref), nb[:, :2], nb[:, 2:], cfg)
        plain = safety.filter_one(*args)
        zero = safety.filter_one(
            *args,
            pos_sigma_m=0.0,
            nbr_pos_sigma_m=np.zeros(len(nb)),
            nbr_cooperative=np.ones(len(nb), bool),
        )
        assert np.array_equal(plain, zero)


def test_uncertainty_widens_the_berth_and_traffic_takes_no_share():
    cfg = safety.SafetyConfig(sigma_k=2.0)  # 3 m, margin 0.2
    r, share = safety.pair_radius_m(cfg, 0.5, np.array([0.5, 0.0]), np.array([True, False]))
    assert r[0] == pytest.approx(3.6 + 2 * math.sqrt(0.5)) and r[1] == pytest.approx(3.6 + 1.0)
    assert share.tolist() == [0.5, 1.0]
    # a neighbour 4.5 m ahead, both standing: exact vehicles may close in, 0.5 m GNSS may not
    pos, vel, pref = np.zeros(2), np.zeros(2), np.array([1.0, 0.0])
    nbr_p, nbr_v = np.array([[4.5, 0.0]]), np.zeros((1, 2))
    free = safety.filter_one(pos, vel, pref, nbr_p, nbr_v, cfg)
    held = safety.filter_one(
        pos, vel, pref, nbr_p, nbr_v, cfg, pos_sigma_m=0.5, nbr_pos_sigma_m=np.array([0.5])
    )
    assert free[0] > 0.0 and held[0] < 0.0  # inside 3.6 + 1.41 m: it backs off
    # head-on at 1 m/s each, 8 m apart: the whole correction against traffic, half otherwise
    nbr_p, nbr_v, vel = np.array([[8.0, 0.1]]), np.array([[-1.0, 0.0]]), np.array([1.0, 0.0])
    coop = safety.filter_one(pos, vel, pref, nbr_p, nbr_v, cfg) - pref
    alone = (
        safety.filter_one(pos, vel, pref, nbr_p, nbr_v, cfg, nbr_cooperative=np.array([False]))
        - pref
    )
    # at least the whole correction, and a step aside to the right (east), not back along the line
    assert np.linalg.norm(alone) >= 0.95 * 2 * np.linalg.norm(coop) and alone[1] > 0.3
    # a fast intruder is seen from further away than a covey vehicle
    far_p, fast_v = np.array([[25.0, 0.2]]), np.array([[-5.0, 0.0]])
    assert np.array_equal(safety.filter_one(pos, vel, pref, far_p, fast_v, cfg), pref)
    dodge = safety.filter_one(pos, vel, pref, far_p, fast_v, cfg, nbr_cooperative=np.array([False]))
    assert not np.array_equal(dodge, pref)


@pytest.fixture(scope="module")
def lib():
    from firmware.cpolicy import load_library

    return load_library()


@needs_cc
def test_c_filter_parity_with_uncertainty_and_traffic(lib, capsys):
    from firmware.csafety import CSafetyFilter

    rng = np.random.default_rng(37)
    errs, n_changed, n_nc = [], 0, 0
    n = 2000
    for _ in range(n):
        c, cfg, s_own, s_nbr, coop = _sky_case(rng)
        nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
        own = np.array(c.own, dtype=np.float64)
        sky = {"pos_sigma_m": s_own, "nbr_pos_sigma_m": s_nbr, "nbr_cooperative": coop}
        r = CSafetyFilter(lib, cfg).evaluate(own[:2], own[2:], c.pref, nb[:, :2], nb[:, 2:], **sky)
        assert r.status == "ok"
        ref = safety.filter_velocity(
            own[:2], own[2:], np.array(c.pref), nb[:, :2], nb[:, 2:], cfg, **sky
        )
        errs.append(np.abs(r.vel_m_s - ref).max() / cfg.max_speed_m_s)
        n_changed += r.changed
        n_nc += int((~coop).any() and r.changed)
    worst = float(np.max(errs))
    assert worst <= PARITY_TOL, worst
    assert n_changed > n // 2 and n_nc > n // 10
    with capsys.disabled():
        print(
            f"\n[C sky filter parity] {n} cases ({n_changed} moved): max |C - numpy| = {worst:.2e}"
        )


@needs_cc
def test_c_refuses_bad_uncertainty_and_config(lib):
    from firmware.csafety import CSafetyFilter

    cfg = safety.SafetyConfig()
    f = CSafetyFilter(lib, cfg)
    args = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), [[5.0, 0.0]], [[0.0, 0.0]])
    assert f.evaluate(*args, nbr_pos_sigma_m=[math.nan]).status == "nonfinite"
    assert f.evaluate(*args, nbr_pos_sigma_m=[-0.1]).status == "range"
    assert f.evaluate(*args, pos_sigma_m=math.inf).status == "nonfinite"
    assert f.evaluate(*args, pos_sigma_m=2000.0).status == "range"
    assert CSafetyFilter(lib, replace(cfg, sigma_k=-1.0)).evaluate(*args).status == "range"
    bad_nc = replace(cfg, non_cooperative_radius_m=0.001)
    assert CSafetyFilter(lib, bad_nc).evaluate(*args).status == "range"


@needs_cc
def test_c_guidance_tick_passes_uncertainty_and_traffic_to_the_filter():
    """covey_guidance_step_sky = covey_guidance_step without them, and filters with them as
    the numpy filter does (on the held velocity)."""
    from firmware.cpolicy import CPolicy

    pol = CPolicy.load(sparse_rule=False)
    plain, sky, none = (pol.onboard(1.0) for _ in range(3))
    rng = np.random.default_rng(38)
    for t in range(12):
        pos = rng.uniform(-2, 2, 2)
        nbr_p = pos + rng.uniform(-6, 6, (4, 2))
        nbr_v = rng.uniform(-1, 1, (4, 2))
        args = (pos, (0.3, 0.1), 0.2, (20.0, 0.0), nbr_p, nbr_v, np.zeros(4))
        now_s = 0.1 * t
        a = plain.step(Observation.shaped(*args), now_s)
        z = none.step(Observation.shaped(*args, Sky(0.0, np.zeros(4))), now_s)
        assert a.status == z.status == "ok" and np.array_equal(a.vel_m_s, z.vel_m_s)
        coop = np.array([True, False, True, True])
        s = sky.step(Observation.shaped(*args, Sky(0.5, np.full(4, 0.5), coop)), now_s)
        assert s.status == "ok"
        held = pol.preferred(pos, (0.3, 0.1), 0.2, (20.0, 0.0), nbr_p, nbr_v, np.zeros(4))
        if t == 0:
            ref = safety.filter_velocity(
                pos,
                np.array([0.3, 0.1]),
                held,
                nbr_p,
                nbr_v,
                pol.safety_cfg,
                pos_sigma_m=0.5,
                nbr_pos_sigma_m=np.full(4, 0.5),
                nbr_cooperative=coop,
            )
            assert np.abs(s.vel_m_s - ref).max() < 1e-5


def _scene(rng, k=5):
    pos = rng.uniform(-2, 2, 2)
    return (
        pos,
        rng.uniform(-0.5, 0.5, 2),
        float(rng.uniform(-np.pi, np.pi)),
        pos + np.array([15.0, 3.0]),
        pos + rng.uniform(-6, 6, (k, 2)),
        rng.uniform(-1, 1, (k, 2)),
        rng.uniform(-np.pi, np.pi, k),
    )


def test_runtime_command_takes_uncertainty_and_traffic():
    from policy.runtime import GuidancePolicy

    pol = GuidancePolicy.load()
    rng = np.random.default_rng(39)
    for _ in range(20):
        args = _scene(rng)
        k = len(args[4])
        plain = pol.command(*args)
        assert np.array_equal(
            plain, pol.command(*args, pos_sigma_m=0.0, nbr_pos_sigma_m=np.zeros(k))
        )
        sky = {
            "pos_sigma_m": 0.5,
            "nbr_pos_sigma_m": np.full(k, 0.5),
            "nbr_cooperative": rng.random(k) > 0.3,
        }
        got = pol.command(*args, **sky)
        held = pol.preferred(*args, **sky)
        want = safety.filter_one(args[0], args[1], held, args[4], args[5], pol.safety_cfg, **sky)
        assert np.allclose(got, want, atol=1e-12)
        # the checked path (lists, not arrays) gives the same
        listed = [a.tolist() if isinstance(a, np.ndarray) else a for a in args]
        assert np.allclose(pol.command(*listed, **sky), got, atol=1e-5)
    args = _scene(rng)
    for bad, match in (
        ({"pos_sigma_m": -1.0}, "pos_sigma_m must be finite and >= 0"),
        ({"pos_sigma_m": math.nan}, "pos_sigma_m must be finite and >= 0"),
        ({"nbr_pos_sigma_m": np.ones(3)}, "nbr_pos_sigma_m must have shape"),
        ({"nbr_pos_sigma_m": -np.ones(5)}, "nbr_pos_sigma_m must be >= 0"),
        ({"nbr_cooperative": np.ones(4, bool)}, "nbr_cooperative must have shape"),
    ):
        with pytest.raises(ValueError, match=match):
            pol.command(*args, **bad)


@needs_cc
def test_cpolicy_command_takes_uncertainty_and_traffic():
    from firmware.cpolicy import CPolicy

    cpol = CPolicy.load()
    rng = np.random.default_rng(40)
    for _ in range(10):
        args = _scene(rng)
        k = len(args[4])
        sky = {
            "pos_sigma_m": 0.4,
            "nbr_pos_sigma_m": rng.uniform(0, 1, k),
            "nbr_cooperative": rng.random(k) > 0.3,
        }
        held = cpol.preferred(*args, **sky)
        got = cpol.command(*args, **sky)
        want = safety.filter_velocity(
            args[0], args[1], held, args[4], args[5], cpol.safety_cfg, **sky
        )
        assert np.abs(got - want).max() < 1e-5
    with pytest.raises(ValueError, match="nbr_pos_sigma_m must be >= 0"):
        cpol.command(*_scene(rng), nbr_pos_sigma_m=-np.ones(5))
