"""A pair inside its uncertainty padding parts at what vehicles can
(policy.safety.RECOVER_SPEED_SHARE), in numpy (both paths) and in C: the demand no longer makes
the program infeasible, so the other neighbours still count. Inside the separation itself, and
without sigmas, nothing changes."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy.safety import RECOVER_SPEED_SHARE, SafetyConfig, filter_one, filter_velocity

ZERO = np.zeros(2)
needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
SIGMA = 0.75  # each; r = 3.6 + 4 sqrt(2) 0.75 = 7.84 m between estimates


CROWD = ([[-6.0, 0.0], [7.0, 0.3]], [[0.0, 0.0], [-1.0, 0.0]])
"""At rest 6 m from a hovering neighbour (1.84 m inside their 7.84 m), while another comes
head-on from the other side at 1 m/s: the neighbours' positions and velocities."""


def _crowded(cfg: SafetyConfig, fn=filter_velocity) -> np.ndarray:
    return fn(ZERO, ZERO, ZERO, *CROWD, cfg, pos_sigma_m=SIGMA, nbr_pos_sigma_m=[SIGMA, SIGMA])


def test_one_pair_inside_parts_at_full_speed_either_way() -> None:
    """Alone with one neighbour 1 m inside the berth: both rules flee at the speed limit (the
    reciprocal half of 2 max speeds is one), so nothing is lost where only one pair overlaps."""
    for share in (0.0, RECOVER_SPEED_SHARE):
        cfg = SafetyConfig(recover_speed_share=share)
        v = filter_velocity(ZERO, ZERO, ZERO, [[-2.6, 0.0]], [[0.0, 0.0]], cfg)
        assert v == pytest.approx([cfg.max_speed_m_s, 0.0], abs=1e-6)


def test_a_small_overlap_is_answered_as_before() -> None:
    """Within one dt of the berth's edge the demand is (r - d) / dt, as RVO2 asks."""
    for share in (0.0, RECOVER_SPEED_SHARE):
        cfg = SafetyConfig(recover_speed_share=share)
        v = filter_velocity(ZERO, ZERO, ZERO, [[-3.55, 0.0]], [[0.0, 0.0]], cfg)
        assert v == pytest.approx([0.5 * 0.05 / cfg.dt_s, 0.0], abs=1e-6)


@pytest.mark.parametrize("fn", [filter_velocity, filter_one], ids=["vectorised", "scalar"])
def test_inside_the_separation_itself_the_demand_is_rvo2s(fn) -> None:
    """3 m from the hovering one, inside the 3.6 m separation and not only its padding: an
    emergency, answered as before (flee it, whatever comes from the other side)."""
    args = (ZERO, ZERO, ZERO, [[-3.0, 0.0], [7.0, 0.3]], [[0.0, 0.0], [-1.0, 0.0]])
    kw = {"pos_sigma_m": SIGMA, "nbr_pos_sigma_m": np.array([SIGMA, SIGMA])}
    before = fn(*args, SafetyConfig(recover_speed_share=0.0), **kw)
    after = fn(*args, SafetyConfig(), **kw)
    assert after == pytest.approx(before, abs=1e-9)
    assert after[0] > 0.9


def test_exact_positions_fly_as_before() -> None:
    """No padding without sigmas: the rule changes nothing (ideal vehicles fly the same)."""
    rng = np.random.default_rng(3)
    for _ in range(300):
        k = int(rng.integers(1, 8))
        args = (ZERO, rng.uniform(-1, 1, 2), rng.uniform(-1.2, 1.2, 2))
        nbrs = (rng.uniform(-6, 6, (k, 2)), rng.uniform(-1, 1, (k, 2)))
        for fn in (filter_velocity, filter_one):
            old = fn(*args, *nbrs, SafetyConfig(recover_speed_share=0.0))
            assert fn(*args, *nbrs, SafetyConfig()) == pytest.approx(old, abs=1e-12)


@pytest.mark.parametrize("fn", [filter_velocity, filter_one], ids=["vectorised", "scalar"])
def test_inside_one_berth_it_no_longer_flees_into_another(fn) -> None:
    """The old demand (18 m/s to leave within 0.1 s) cannot be met, and the fallback that
    minimises the worst violation then flees straight at the vehicle coming head-on; capped,
    the demand is met beside the other's, and the vehicle steps aside."""
    before = _crowded(SafetyConfig(recover_speed_share=0.0), fn)
    after = _crowded(SafetyConfig(), fn)
    assert before == pytest.approx([1.0, 0.0], abs=1e-6), "towards the one coming head-on"
    assert after[0] < 0.0, "not towards it"
    assert abs(after[1]) > 0.9, "aside, at about the speed limit"


@pytest.fixture(scope="module")
def lib():
    from firmware.cpolicy import CPolicy

    return CPolicy.load(sparse_rule=False)._lib


@needs_cc
def test_c_parts_as_numpy(lib) -> None:
    from firmware.csafety import CSafetyFilter

    rng = np.random.default_rng(5)
    for share in (0.0, 1.0, RECOVER_SPEED_SHARE):
        cfg = SafetyConfig(recover_speed_share=share)
        c = CSafetyFilter(lib, cfg)
        assert c.evaluate(*_crowded_args()).status == "ok"
        for _ in range(200):
            k = int(rng.integers(1, 8))
            nbr = rng.uniform(-9, 9, (k, 2))
            nv = rng.uniform(-1, 1, (k, 2))
            own_v, pref = rng.uniform(-1, 1, 2), rng.uniform(-1.2, 1.2, 2)
            sig = rng.uniform(0, 1.2, k)
            ref = filter_velocity(
                ZERO, own_v, pref, nbr, nv, cfg, pos_sigma_m=0.6, nbr_pos_sigma_m=sig
            )
            got = c.evaluate(ZERO, own_v, pref, nbr, nv, pos_sigma_m=0.6, nbr_pos_sigma_m=sig)
            assert got.status == "ok"
            assert got.vel_m_s == pytest.approx(ref, abs=2e-4)
    crowded = CSafetyFilter(lib, SafetyConfig()).evaluate(*_crowded_args())
    assert crowded.vel_m_s == pytest.approx(_crowded(SafetyConfig()), abs=2e-4)


def test_a_bad_share_is_refused_with_the_reason() -> None:
    for bad in (-0.5, 11.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="recover_speed_share=.* must be within"):
            SafetyConfig(recover_speed_share=bad)


@needs_cc
def test_the_c_config_refuses_a_bad_share(lib) -> None:
    from firmware.csafety import CSafetyFilter

    for bad, why in ((-0.5, "range"), (11.0, "range"), (float("nan"), "nonfinite")):
        filt = CSafetyFilter(lib, SafetyConfig())
        filt._ccfg.recover_speed_share = bad  # what only a C caller could pass
        got = filt.evaluate(ZERO, ZERO, ZERO, [[5.0, 0.0]], [[0.0, 0.0]])
        assert got.status == why
        assert not got.vel_m_s.any(), "a refused call commands nothing"


def _crowded_args() -> tuple:
    """CROWD as CSafetyFilter.evaluate takes it (no ids)."""
    return (ZERO, ZERO, ZERO, *CROWD, 0, None, SIGMA, np.array([SIGMA, SIGMA]))
