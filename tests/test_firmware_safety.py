"""The C separation filter (covey_safety.c) and guidance tick (covey_guidance.c).

- parity with policy/safety.py on shared float32 vectors (feasible and infeasible crowds);
- fuzz under ASan + UBSan: every hostile input gets exactly the predicted fault, never a crash;
- the decision hold: decide at the trained period, filter every tick, as agent/guidance.py;
- CPolicy.command with the filter = the numpy filter on the C network's output.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from firmware import hostbuild
from firmware import safety_cases as sc
from firmware.cases import STATUS
from policy import safety
from policy.observation import Observation

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")

N_PARITY = 3000
N_FUZZ_VALID = 300
N_FUZZ_MUTATED = 8000
PARITY_TOL = 1e-6
"""Max |C - numpy| per component, as a share of max_speed (measured 4e-8: float32 output)."""


@pytest.fixture(scope="module")
def cpol():
    """The network and the filter, without the sparse rule (tests/test_policy_sparse.py)."""
    from firmware.cpolicy import CPolicy

    return CPolicy.load(sparse_rule=False)


def _bare(cpol):
    """cpol's network alone, told the same separation."""
    from firmware.cpolicy import CPolicy

    return CPolicy.load(safety_filter=False, policy_separation_m=cpol._cfg.separation_m)


def _ref(c: sc.FilterCase) -> np.ndarray:
    nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
    own = np.array(c.own, dtype=np.float64)
    cfg = safety.SafetyConfig(*c.cfg)
    return safety.filter_velocity(own[:2], own[2:], np.array(c.pref), nb[:, :2], nb[:, 2:], cfg)


def test_filter_parity_with_numpy(cpol, capsys):
    from firmware.csafety import CSafetyFilter

    rng = np.random.default_rng(16)
    errs, n_changed, n_infeasible = [], 0, 0
    for _ in range(N_PARITY):
        c = sc.random_case(rng, scale=float(rng.choice([0.5, 1.0, 3.0])))
        cfg = safety.SafetyConfig(*c.cfg)
        nb = np.array(c.nbrs, dtype=np.float64).reshape(-1, 4)
        r = CSafetyFilter(cpol._lib, cfg).evaluate(
            c.own[:2], c.own[2:], c.pref, nb[:, :2], nb[:, 2:]
        )
        assert r.status == "ok"
        ref = _ref(c)
        errs.append(np.abs(r.vel_m_s - ref).max() / cfg.max_speed_m_s)
        assert np.hypot(*r.vel_m_s) <= cfg.max_speed_m_s * (1 + 1e-6)
        n_changed += r.changed
        n_infeasible += r.infeasible
    worst = float(np.max(errs))
    assert worst <= PARITY_TOL, worst
    # the vectors reach every branch: untouched, moved, infeasible (the fallback LP)
    assert n_changed > N_PARITY // 2 and n_infeasible > N_PARITY // 10
    assert n_changed < N_PARITY
    with capsys.disabled():
        print(
            f"\n[C filter parity] {N_PARITY} cases ({n_changed} moved, {n_infeasible} infeasible):"
            f" max |C - numpy| = {worst:.2e} of max speed"
        )


def test_filter_keeps_a_head_on_pair_apart(cpol):
    """Two vehicles nose to nose at 1 m/s: the filtered velocity leaves the collision course."""
    v = cpol.filter([0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [[6.0, 0.0]], [[-1.0, 0.0]])
    assert abs(v[1]) > 0.1  # it steers sideways
    assert np.allclose(v, _ref(sc.FilterCase(own=(0, 0, 1, 0), pref=(1, 0), nbrs=[(6, 0, -1, 0)])))
    # far away: untouched, only the speed clipped
    v = cpol.filter([0.0, 0.0], [0.0, 0.0], [3.0, 4.0], [[500.0, 0.0]], [[0.0, 0.0]])
    assert np.allclose(v, [0.6, 0.8], atol=1e-6)


def test_tie_direction_is_one_line_each_its_own_way_and_spreads():
    """The pair (a, b) gets one bearing; b sees the opposite; different pairs spread."""
    for a, b in [(1, 2), (1, 7), (3, 250), (4_000_000_000, 5)]:
        da, db = np.array(safety.tie_direction(a, b)), np.array(safety.tie_direction(b, a))
        assert np.isclose(np.hypot(*da), 1.0) and np.allclose(da, -db)
    bearings = {round(float(np.arctan2(*safety.tie_direction(1, k)[::-1])), 1) for k in range(2, 9)}
    assert len(bearings) == 7


def test_coincident_vehicles_are_pushed_apart_by_id_in_c_as_in_numpy(cpol):
    """Two vehicles at one point with the same velocity (after a take-off from one spot): the
    relative position and velocity are zero, so ORCA has no direction and, without ids, leaves
    both where they are (the 0.0 m hover of issue 39). With ids, each is pushed its own way
    along the pair's bearing, at full speed, in C as in numpy (parity), and the two ways are
    opposite."""
    from firmware.csafety import CSafetyFilter

    cfg = cpol.safety_cfg
    filt = CSafetyFilter(cpol._lib, cfg)
    rng = np.random.default_rng(39)
    errs = []
    for k in range(300):
        p = rng.uniform(-50, 50, 2).astype(np.float32).astype(np.float64)
        v = rng.uniform(-0.3, 0.3, 2).astype(np.float32).astype(np.float64) * (k % 2)
        off = rng.uniform(-1, 1, 2) * safety.COINCIDENT_M * 0.5 * (k % 3 == 0)
        q = (p + off).astype(np.float32).astype(np.float64)
        pref = rng.uniform(-0.5, 0.5, 2).astype(np.float32).astype(np.float64)
        a, b = (int(x) for x in rng.choice(np.arange(1, 400), 2, replace=False))
        # others farther off, without ids and with
        extra = (p + rng.uniform(6, 9, (2, 2))).astype(np.float32).astype(np.float64)
        nb_pos = np.vstack([q, extra])
        nb_vel = np.vstack([v, np.zeros((2, 2))])
        ids = [b, 0, b + 1]
        c = filt.evaluate(p, v, pref, nb_pos, nb_vel, a, ids)
        ref = safety.filter_velocity(p, v, pref, nb_pos, nb_vel, cfg, a, ids)
        fast = safety.filter_one(p, v, pref, nb_pos, nb_vel, cfg, a, ids)
        assert c.status == "ok"
        errs.append(np.abs(c.vel_m_s - ref).max() / cfg.max_speed_m_s)
        assert np.allclose(fast, ref, atol=1e-12)
    assert max(errs) <= PARITY_TOL, max(errs)

    # exactly coincident, both at rest, both asked to stay: before, no push at all
    zero = np.zeros(2)
    still = filt.evaluate(zero, zero, zero, [zero], [zero])
    assert np.allclose(still.vel_m_s, 0.0), "no ids: no direction (the old behaviour)"
    va = filt.evaluate(zero, zero, zero, [zero], [zero], 1, [7]).vel_m_s
    vb = filt.evaluate(zero, zero, zero, [zero], [zero], 7, [1]).vel_m_s
    assert np.hypot(*va) > 0.9 * cfg.max_speed_m_s
    assert np.allclose(va, -vb, atol=1e-6)
    assert np.dot(va, np.array(safety.tie_direction(1, 7))) < 0, "away from the neighbour"
    pad = safety.filter_batch(
        np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)), np.array([[1], [0]]), cfg, [1, 7]
    )
    np.testing.assert_allclose(pad, [va, vb], atol=1e-6)


def test_filter_fuzz_under_sanitizers(capsys, fuzz_drivers):
    asan, plain = fuzz_drivers
    rng = np.random.default_rng(61)
    valid = [sc.random_case(rng) for _ in range(N_FUZZ_VALID)]
    mutated = []
    for k in range(N_FUZZ_MUTATED):
        base = sc.random_case(rng, n_nbrs=None if k % 20 == 0 else int(rng.integers(0, 5)))
        mutated.append(sc.mutate(base, rng))
    all_cases = valid + mutated
    text = "\n".join(map(sc.line, all_cases)) + "\n"
    lines, stderr = hostbuild.run_driver(asan, text)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr[-2000:]
    assert len(lines) == len(all_cases)
    assert hostbuild.run_driver(plain, text)[0] == lines  # same bits as the -O2 build

    counts = dict.fromkeys(STATUS, 0)
    for c, text_line in zip(all_cases, lines, strict=True):
        out = sc.parse_output(text_line)
        expect = sc.expected_status(c)
        assert out["status"] == expect, (text_line, c)
        counts[next(k for k, v in STATUS.items() if v == expect)] += 1
        assert np.all(np.isfinite(out["vel"]))
        if expect == STATUS["ok"]:
            assert np.hypot(*out["vel"]) <= float(np.float32(c.cfg[4])) * (1 + 1e-6)
        else:
            assert not np.any(out["vel"]), "a fault must command zero velocity"
    assert counts["ok"] >= N_FUZZ_VALID and counts["nonfinite"] > 500 and counts["range"] > 500
    with capsys.disabled():
        print(
            f"\n[C filter fuzz] {len(all_cases)} inputs ({len(mutated)} mutated) under ASan+UBSan:"
            f" statuses {counts}, clean"
        )


def _scene(rng, n=6):
    pos = rng.uniform(-8, 8, (n, 2))
    vel = rng.uniform(-0.7, 0.7, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    return pos, vel, heading


def test_command_with_filter_is_the_filter_of_the_network(cpol):
    bare = _bare(cpol)
    rng = np.random.default_rng(3)
    moved = 0
    for _ in range(100):
        pos, vel, hdg = _scene(rng)
        goal = rng.uniform(-20, 20, 2)
        args = (pos[0], vel[0], hdg[0], goal, pos[1:], vel[1:], hdg[1:])
        v_net = bare.command(*args)
        v = cpol.command(*args)
        ref = safety.filter_velocity(pos[0], vel[0], v_net, pos[1:], vel[1:], cpol.safety_cfg)
        assert np.abs(v - ref).max() <= 1e-5  # float64 inputs rounded to float32 in C
        moved += not np.allclose(v, v_net)
    assert moved > 10


def test_onboard_decides_at_the_trained_period_and_filters_every_tick(cpol):
    """covey_guidance_step against agent/guidance.py's rule, reimplemented here in numpy:
    decide when 95 % of the period has passed (or the goal changed), filter every tick."""
    from firmware.cpolicy import CPolicy

    bare = _bare(cpol)
    assert cpol.decision_period_s == pytest.approx(1.0)
    assert CPolicy.load(separation_m=6.0, cruise_speed_m_s=2.0).decision_period_s == pytest.approx(
        1.0
    )
    assert CPolicy.load(separation_m=6.0).decision_period_s == pytest.approx(2.0)
    tick = cpol.onboard()
    rng = np.random.default_rng(5)
    pos, vel, hdg = _scene(rng)
    goal = np.array([30.0, 5.0])
    decided_at, held = [], None
    for k in range(31):
        t = 0.1 * k
        if k == 25:
            goal = np.array([-30.0, 0.0])  # a new goal decides at once
        pos = pos + 0.1 * vel
        vel = vel + rng.normal(0, 0.05, vel.shape)
        r = tick.step(
            Observation.shaped(pos[0], vel[0], hdg[0], goal, pos[1:], vel[1:], hdg[1:]), t
        )
        assert r.status == "ok"
        if r.decided:
            decided_at.append(round(t, 1))
            held = bare.command(pos[0], vel[0], hdg[0], goal, pos[1:], vel[1:], hdg[1:])
        ref = safety.filter_velocity(pos[0], vel[0], held, pos[1:], vel[1:], cpol.safety_cfg)
        assert np.abs(r.vel_m_s - ref).max() <= 1e-5, (t, r, ref)
    assert decided_at == [0.0, 1.0, 2.0, 2.5]


def test_onboard_faults_hover_and_forget_the_hold(cpol):
    tick = cpol.onboard()
    p = np.zeros(2)
    nbr = np.array([[4.0, 0.0]])

    def seen(nbr_vel_m_s):
        return Observation.shaped(p, [1.0, 0.0], 0.0, [50.0, 0.0], nbr, nbr_vel_m_s, [np.pi])

    ok = tick.step(seen([[-1.0, 0.0]]), now_s=1.0)
    assert ok.status == "ok" and ok.decided
    bad = tick.step(seen([[np.nan, 0.0]]), now_s=1.1)
    assert bad.status == "nonfinite" and not np.any(bad.vel_m_s)
    stale = tick.step(seen([[-1.0, 0.0]]), now_s=1.2, stamp_s=0.1)
    assert stale.status == "stale" and not np.any(stale.vel_m_s)
    again = tick.step(seen([[-1.0, 0.0]]), now_s=1.3)
    assert again.status == "ok" and again.decided  # the fault dropped the held decision
    # a stale neighbour is dropped from the filter, not a fault
    r = tick.step(seen([[-1.0, 0.0]]), now_s=5.0, nbr_stamp_s=[1.0])
    assert r.status == "ok" and not r.filtered


def test_policy_separation_scales_the_network_not_the_filter():
    """policy_separation_m changes what the network sees; the filter keeps separation_m."""
    from firmware.cpolicy import CPolicy

    wide = CPolicy.load(separation_m=3.0, policy_separation_m=2.0, safety_filter=False)
    scaled = CPolicy.load(separation_m=2.0, safety_filter=False)
    rng = np.random.default_rng(9)
    pos, vel, hdg = _scene(rng)
    args = (pos[0], vel[0], hdg[0], [20.0, 3.0], pos[1:], vel[1:], hdg[1:])
    np.testing.assert_array_equal(wide.command(*args), scaled.command(*args))
    filt = CPolicy.load(separation_m=3.0, policy_separation_m=2.0)
    assert filt.safety_cfg.radius_m == 3.0


def test_safety_defaults_in_c_are_the_runtimes(cpol):
    """covey_safety_defaults (what the PX4 module and the emulator's onboard mode fly) is
    policy.safety.SafetyConfig at the same separation and speed, field by field: one filter
    setting in C and Python (the margin included, raised to 0.2 in issue 16)."""
    for sep_m, vmax in ((3.0, 1.0), (5.0, 12.0)):
        c = cpol._lib.covey_safety_defaults(sep_m, vmax)
        ref = safety.SafetyConfig(radius_m=sep_m, max_speed_m_s=vmax)
        for name, _ in type(c)._fields_:
            want = getattr(ref, name)
            want = 0.0 if want is None else want  # None (non_cooperative_radius_m) is 0 in C
            assert getattr(c, name) == pytest.approx(want, rel=1e-6), name


def test_told_separation_in_c_is_the_runtimes(cpol):
    """covey_told_separation_m (the PX4 module's CVY_POL_SEP_M, 0 = default) is
    policy.runtime.told_separation_m (None = default): one rule for the berth, in C and Python."""
    from policy.runtime import FILTERED_BERTH_SHARE, told_separation_m

    told = cpol._lib.covey_told_separation_m
    for sep in (0.5, 3.0, 7.5):
        for filt in (0, 1):
            for asked in (None, 0.8, 4.0):
                c = told(sep, filt, 0.0 if asked is None else asked)
                assert c == pytest.approx(told_separation_m(sep, bool(filt), asked), rel=1e-6)
    assert (
        told(3.0, 1, 0.0) == pytest.approx(3.0 * FILTERED_BERTH_SHARE) and told(3.0, 0, 0.0) == 3.0
    )
    assert np.isnan(told(3.0, 1, float("nan")))  # passed on for covey_config_check to refuse
