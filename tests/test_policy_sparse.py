"""The sparse-traffic rule (policy/sparse.py): which encounters fly straight, the same answer on
every runtime path and in C (covey_sparse_choose), and what it buys in flight."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from policy import evalsim, safety, sparse
from policy.observation import Observation, Observations, Swarm
from policy.runtime import GuidancePolicy

CFG = sparse.SparseConfig()
SAFE = safety.SafetyConfig()  # 3 m, 1 m/s: the trained period is 1 s
GOAL = np.array([40.0, 0.0])
ASKED = np.array([0.6, 0.6])  # what the "policy" asked for, distinct from any straight line


def _choose(nbr_pos, nbr_vel, pos=(0.0, 0.0), vel=(1.0, 0.0), goal=GOAL):
    return sparse.choose_one(pos, vel, goal, ASKED, nbr_pos, nbr_vel, SAFE, CFG, 1.0)


def test_alone_flies_straight_at_cruise_and_slows_to_stop_on_the_goal():
    v, straight = _choose(np.zeros((0, 2)), np.zeros((0, 2)))
    assert straight and np.allclose(v, [1.0, 0.0])
    v, straight = _choose(np.zeros((0, 2)), np.zeros((0, 2)), pos=(39.6, 0.0))
    assert straight and np.allclose(v, [0.4, 0.0])  # reaches the goal in one period


def test_two_crossings_fly_straight_but_dead_on_three_or_blocked_fly_the_policy():
    # a neighbour crossing 2 m behind us (closest approach ~1.4 m): one encounter, not dead-on
    v, straight = _choose([[12.0, -10.0]], [[0.0, 1.0]])
    assert straight and np.allclose(v, [1.0, 0.0])
    # dead-on: it reaches the crossing when we do
    v, straight = _choose([[10.0, -10.0]], [[0.0, 1.0]])
    assert not straight and np.allclose(v, ASKED)
    # head-on on our line: dead-on too
    _, straight = _choose([[20.0, 0.0]], [[-1.0, 0.0]])
    assert not straight
    # two encounters at once (crossing behind us from either side): still sparse
    _, straight = _choose([[12.0, -10.0], [12.0, 10.0]], [[0.0, 1.0], [0.0, -1.0]])
    assert straight
    # three at once: dense traffic
    _, straight = _choose(
        [[12.0, -10.0], [12.0, 10.0], [14.0, -12.0]], [[0.0, 1.0], [0.0, -1.0], [0.0, 1.0]]
    )
    assert not straight
    # and with one encounter allowed, as before, two are dense
    _, straight = sparse.choose_one(
        (0.0, 0.0),
        (1.0, 0.0),
        GOAL,
        ASKED,
        [[12.0, -10.0], [12.0, 10.0]],
        [[0.0, 1.0], [0.0, -1.0]],
        SAFE,
        sparse.SparseConfig(max_encounters=1),
        1.0,
    )
    assert not straight
    # far away or diverging: no encounter at all
    _, straight = _choose([[0.0, 30.0], [-10.0, 0.0]], [[0.0, 1.0], [-1.0, 0.0]])
    assert straight
    # beyond the horizon (10 periods): not yet an encounter
    _, straight = _choose([[25.0, -25.0]], [[0.0, 1.0]])
    assert straight
    # someone near already (3.6 m off) while the policy has us turned aside: the policy keeps
    # its berth, rather than turning at the neighbour with the filter alone at its margin
    _, straight = _choose([[0.0, 3.6]], [[1.0, 0.0]], vel=(0.5, 0.8))
    assert not straight
    _, straight = _choose([[0.0, 6.5]], [[1.0, 0.0]], vel=(0.5, 0.8))
    assert straight  # nobody within 2 separations
    _, straight = _choose([[0.0, 3.6]], [[1.0, 0.0]], vel=(0.95, 0.2))
    assert straight  # already flying along the straight line (within 25 degrees)


def test_the_line_ends_at_the_goal_unless_someone_is_there():
    """Encounters are looked for only until the straight line reaches the goal; when a
    neighbour is within one separation of the goal now, over the whole horizon, so that one
    standing on it or pushed just past it is dead-on and left to the policy."""
    goal = np.array([6.0, 0.0])  # 6 s away at 1 m/s
    # it crosses our line dead-on 10 m out: past this goal, so not dead-on for it
    v, straight = _choose([[10.0, -10.0]], [[0.0, 1.0]], goal=goal)
    assert straight and np.allclose(v, [1.0, 0.0])
    _, straight = _choose([[10.0, -10.0]], [[0.0, 1.0]])  # the goal beyond: dead-on
    assert not straight
    # standing on our line 4 m past the goal: the line ends 4 m from it, one encounter
    _, straight = _choose([[10.0, 0.0]], [[0.0, 0.0]], goal=goal)
    assert straight
    # 2 m past the goal: within one separation of it, the goal is taken, the whole horizon
    # sees it dead-on ahead: the policy
    assert sparse.goal_taken(goal, [[8.0, 0.0]], [True], 3.0)
    v, straight = _choose([[8.0, 0.0]], [[0.0, 0.0]], goal=goal)
    assert not straight and np.allclose(v, ASKED)
    # and the horizon is cut only where the goal is free
    cut = sparse.encounter_horizon_s(
        np.zeros((2, 2)), np.tile(goal, (2, 1)), np.array([False, True]), CFG, 1.0, 1.0
    )
    assert np.allclose(cut, [6.0, 10.0])
    # passing 0.7 m from the goal when we arrive, 5 m from it now: an encounter, straight
    _, straight = _choose([[6.0, -5.0]], [[0.0, 1.0]], goal=goal)
    assert straight


def test_the_straight_line_must_keep_its_progress_through_the_filter():
    """An encounter the filter bends (a vehicle crossing 1 m off, 7 m ahead): flown straight
    only if the filtered straight line keeps progress_share of its speed towards the goal."""
    nbr, nbr_vel = [[7.0, -4.0]], [[0.0, 1.0]]
    f = safety.filter_velocity([0.0, 0.0], [1.0, 0.0], [1.0, 0.0], nbr, nbr_vel, SAFE)
    assert 0.0 < f[0] < 0.999  # the filter slows or bends the straight line
    for share, expect in ((0.0, True), (float(f[0]) - 0.01, True), (float(f[0]) + 0.01, False)):
        cfg = sparse.SparseConfig(progress_share=share)
        _, straight = sparse.choose_one(
            [0.0, 0.0], [1.0, 0.0], GOAL, ASKED, nbr, nbr_vel, SAFE, cfg, 1.0
        )
        assert straight is expect, share


def test_config_is_validated():
    for bad in (
        {"horizon_periods": -1.0},
        {"encounter_separations": math.nan},
        {"progress_share": 1.5},
        {"max_encounters": -1},
        {"clear_separations": -0.5},
        {"aligned_cos": 1.5},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            sparse.SparseConfig(**bad)


def _scenes(rng, n_scenes=60, n=6):
    for _ in range(n_scenes):
        pos = rng.uniform(-15, 15, (n, 2))
        vel = rng.uniform(-1, 1, (n, 2)) * 0.7
        heading = rng.uniform(-np.pi, np.pi, n)
        goal = rng.uniform(-40, 40, (n, 2))
        yield pos, vel, heading, goal


def test_every_runtime_path_applies_the_same_rule():
    """command (one vehicle), command_batch of Observations (padded views, as agents and eval
    decide) and of a Swarm give the same velocities with the rule on, and differ from the policy's
    where the rule flew straight."""
    on = GuidancePolicy.load(safety_filter=False, sparse_rule=CFG)
    off = GuidancePolicy.load(safety_filter=False)
    rng = np.random.default_rng(16)
    n_straight = n_policy = 0
    for pos, vel, h, goal in _scenes(rng):
        n = len(pos)
        batch = on.command_batch(Swarm.checked(pos, vel, h, goal))
        idx = np.array([[j for j in range(n) if j != i] for i in range(n)])
        views = on.command_batch(
            Observations(pos, vel, h, goal, pos[idx], vel[idx], h[idx], np.ones(idx.shape, bool))
        )
        for i in range(n):
            o = idx[i]
            one = on.command(pos[i], vel[i], h[i], goal[i], pos[o], vel[o], h[o])
            np.testing.assert_allclose(views[i], one, atol=2e-6)
            np.testing.assert_allclose(batch[i], one, atol=2e-6)
            _, straight = sparse.choose_one(
                pos[i], vel[i], goal[i], one, pos[o], vel[o], on.safety_cfg, CFG, 1.0
            )
            pol = off.command(pos[i], vel[i], h[i], goal[i], pos[o], vel[o], h[o])
            if straight:
                n_straight += 1
                v_s = sparse.straight_velocity(pos[i], goal[i], 1.0, 1.0)
                np.testing.assert_allclose(one, v_s, atol=1e-12)
            else:
                n_policy += 1
                np.testing.assert_allclose(one, pol, atol=1e-12)
    assert n_straight > 20 and n_policy > 20


def test_agent_guidance_flies_the_rule_only_with_the_filter():
    from agent.guidance import GuidanceConfig

    assert GuidanceConfig().load_policy().sparse_rule == CFG
    assert GuidanceConfig(sparse_rule=False).load_policy().sparse_rule is None
    assert GuidanceConfig(safety_filter=False).load_policy().sparse_rule is None


def test_runtime_defaults_fly_as_the_agents():
    """GuidancePolicy.load() with its defaults is what an agent flies (GuidanceConfig(): told
    the weights' share of the separation, the sparse rule, then the filter), so that any caller of the
    runtime gets flight's behaviour; without the filter: the whole separation, no rule."""
    from agent.guidance import GuidanceConfig
    from policy.runtime import FILTERED_BERTH_SHARE

    pol = GuidancePolicy.load()
    assert pol.sparse_rule == CFG and pol.safety_filter
    assert pol.dist_scale_m == pytest.approx(FILTERED_BERTH_SHARE)
    bare = GuidancePolicy.load(safety_filter=False)
    assert bare.sparse_rule is None and bare.dist_scale_m == pytest.approx(1.0)
    assert GuidancePolicy.load(sparse_rule=False).sparse_rule is None
    with pytest.raises(TypeError, match="sparse_rule"):
        GuidancePolicy.load(sparse_rule="on")
    agent = GuidanceConfig().load_policy()  # unfiltered: the agent filters every tick itself
    rng = np.random.default_rng(23)
    n_straight = 0
    for p, v, h, g in _scenes(rng):
        o = np.arange(1, len(p))
        args = (p[0], v[0], h[0], g[0], p[o], v[o], h[o])
        want = agent.command(*args)
        if len(o):
            want = safety.filter_velocity(p[0], v[0], want, p[o], v[o], agent.safety_cfg)
        np.testing.assert_allclose(pol.command(*args), want, atol=1e-12)
        n_straight += sparse.choose_one(p[0], v[0], g[0], want, p[o], v[o], SAFE, CFG, 1.0)[1]
    assert n_straight > 5


def test_preferred_is_what_the_agents_hold_and_command_filters_it():
    """`preferred` (the velocity to hold for a decision period) is the agents' decision, before
    the filter; `command` is the filter of it. Same on the checked path (lists in)."""
    from agent.guidance import GuidanceConfig

    pol, agent = GuidancePolicy.load(), GuidanceConfig().load_policy()
    rng = np.random.default_rng(31)
    n_filtered = 0
    for p, v, h, g in _scenes(rng, n_scenes=40):
        o = np.arange(1, len(p))
        args = (p[0], v[0], h[0], g[0], p[o], v[o], h[o])
        held = pol.preferred(*args)
        np.testing.assert_array_equal(held, agent.command(*args))
        listed = [x.tolist() if isinstance(x, np.ndarray) else x for x in args]
        np.testing.assert_allclose(pol.preferred(*listed), held, atol=1e-5)
        now = pol.filter(p[0], v[0], held, p[o], v[o])
        np.testing.assert_allclose(pol.command(*args), now, atol=1e-12)
        n_filtered += not np.allclose(now, held)
    assert n_filtered > 5
    with pytest.raises(ValueError, match="goal_m"):
        pol.preferred(p[0], v[0], h[0], [np.nan, 0.0], p[o], v[o], h[o])


def test_agent_cli_switches_the_rule():
    from agent.agent_cli import guidance_from_args, parser

    assert guidance_from_args(parser().parse_args(["--id", "1"])).sparse_rule is True
    args = parser().parse_args(["--id", "1", "--no-sparse-rule"])
    assert guidance_from_args(args).sparse_rule is False


def _fly(controller, starts, goals, link=evalsim.PERFECT):
    return evalsim.run(
        np.asarray(starts, float),
        np.asarray(goals, float),
        controller,
        link,
        evalsim.EvalSimConfig(),
        np.random.default_rng(0),
    )


def _controllers(rule: bool):
    from policy.eval import EvalConfig, controllers

    return controllers(EvalConfig(figures=False, progress=False, sparse_rule=rule))


@pytest.mark.slow
def test_a_lone_crossing_is_faster_and_a_circle_still_flows():
    """Two vehicles crossing at 60 degrees, one 1 m behind: the rule flies it as ORCA does
    (the later one slows a little) instead of the policy's early, wide turn. Eight on a circle,
    where ORCA alone deadlocks: the rule leaves it to the policy, and all arrive."""
    u = np.array([math.cos(math.pi / 3), math.sin(math.pi / 3)])
    starts, goals = [[-30.0, 0.0], -31.0 * u], [[30.0, 0.0], 30.0 * u]
    with_rule = _fly(_controllers(True)["policy+filter"], starts, goals)
    without = _fly(_controllers(False)["policy+filter"], starts, goals)
    assert with_rule["collisions"] == 0 and with_rule["success"] == 1.0
    assert with_rule["extra_time"] < without["extra_time"] - 0.01
    from policy.scenarios import antipodal_circle

    s, g = antipodal_circle(8)
    circle = _fly(_controllers(True)["policy+filter"], s, g, evalsim.DEGRADED)
    assert circle["collisions"] == 0 and circle["success"] == 1.0
    assert circle["min_sep"] >= 3.0


needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


@needs_cc
def test_c_rule_is_the_numpy_rule():
    """covey_sparse_choose against policy.sparse.choose_one on float32-exact random encounters:
    the same choice, and the same velocity, away from the thresholds (within 1e-4 of one,
    float32 rounding may fall either side)."""
    from firmware.cpolicy import CPolicy

    cpol = CPolicy.load(sparse_rule=True)
    filt = cpol._filter
    rng = np.random.default_rng(7)
    agree = near = n_straight = 0
    for _ in range(2000):
        k = int(rng.integers(0, 4))
        f32 = lambda a: np.asarray(a, np.float32).astype(np.float64)  # noqa: E731
        pos, vel = f32(rng.uniform(-5, 5, 2)), f32(rng.uniform(-1, 1, 2))
        goal = f32(rng.uniform(-40, 40, 2))
        asked = f32(rng.uniform(-1, 1, 2))
        nbr_pos, nbr_vel = f32(rng.uniform(-20, 20, (k, 2))), f32(rng.uniform(-1, 1, (k, 2)))
        c = filt.sparse(pos, vel, goal, asked, nbr_pos, nbr_vel)
        assert c.status == "ok"
        ref, straight = sparse.choose_one(
            pos, vel, goal, asked, nbr_pos, nbr_vel, cpol.safety_cfg, CFG, 1.0
        )
        v_s = sparse.straight_velocity(pos, goal, 1.0, 1.0)
        taken = sparse.goal_taken(goal, nbr_pos, np.ones(k, bool), 3.0)
        horizon_s = sparse.encounter_horizon_s(pos, goal, taken, CFG, 1.0, 1.0)
        count, _, _ = sparse.encounters(
            pos, v_s, nbr_pos, nbr_vel, np.ones(k, bool), horizon_s, 6.0, 0.25, np.full(k, 3.6)
        )
        if c.straight != straight:
            near += 1
            continue
        agree += 1
        n_straight += straight
        assert c.n_encounters == count or near
        np.testing.assert_allclose(c.vel_m_s, ref, atol=1e-5)
    assert near <= 4 and agree >= 1990 and 200 < n_straight < 1900


@needs_cc
def test_c_rule_ends_the_line_unless_someone_is_there():
    """The C twin on the scenes of test_the_line_ends_at_the_goal_unless_someone_is_there."""
    from firmware.cpolicy import CPolicy

    filt = CPolicy.load(sparse_rule=True)._filter
    goal = np.array([6.0, 0.0])
    for nbr, nbr_vel, expect in (
        ([[10.0, -10.0]], [[0.0, 1.0]], True),  # dead-on past the goal
        ([[10.0, 0.0]], [[0.0, 0.0]], True),  # standing 4 m past the goal
        ([[8.0, 0.0]], [[0.0, 0.0]], False),  # 2 m past it: taken, dead-on
        ([[6.0, -5.0]], [[0.0, 1.0]], True),
    ):
        c = filt.sparse((0.0, 0.0), (1.0, 0.0), goal, ASKED, np.array(nbr), np.array(nbr_vel))
        assert c.status == "ok" and bool(c.straight) is expect, (nbr, c)
        _, ref = _choose(nbr, nbr_vel, goal=goal)
        assert ref is expect


@needs_cc
def test_c_policy_defaults_are_the_runtime_defaults():
    """CPolicy.load() tells the network what GuidancePolicy.load() does and flies the rule with
    its filter; without the filter, neither."""
    from firmware.cpolicy import CPolicy

    c, py = CPolicy.load(), GuidancePolicy.load()
    assert c.sparse_rule and c.safety_filter
    assert c._cfg.separation_m == pytest.approx(3.0 * py.dist_scale_m)
    bare = CPolicy.load(safety_filter=False)
    assert not bare.sparse_rule and bare._cfg.separation_m == pytest.approx(3.0)
    rng = np.random.default_rng(29)
    worst, n = 0.0, 0
    for p, v, h, g in _scenes(rng):
        o = np.arange(1, len(p))
        args = (p[0], v[0], h[0], g[0], p[o], v[o], h[o])
        worst = max(worst, float(np.abs(c.command(*args) - py.command(*args)).max()))
        n += 1
    assert n > 20 and worst <= 1e-4, worst  # float32; no choice fell on a threshold here


@needs_cc
def test_c_preferred_is_the_runtime_preferred():
    """CPolicy.preferred = GuidancePolicy.preferred (float32), and its filter is `command`."""
    from firmware.cpolicy import CPolicy

    c, py = CPolicy.load(), GuidancePolicy.load()
    rng = np.random.default_rng(37)
    worst = 0.0
    for p, v, h, g in _scenes(rng, n_scenes=30):
        o = np.arange(1, len(p))
        args = (p[0], v[0], h[0], g[0], p[o], v[o], h[o])
        held = c.preferred(*args)
        worst = max(worst, float(np.abs(held - py.preferred(*args)).max()))
        np.testing.assert_allclose(c.filter(p[0], v[0], held, p[o], v[o]), c.command(*args))
    assert worst <= 1e-4, worst


@needs_cc
def test_c_rule_refuses_bad_input_by_name():
    from firmware.cpolicy import CPolicy

    filt = CPolicy.load(sparse_rule=True)._filter
    ok = ([0.0, 0.0], [1.0, 0.0], [30.0, 0.0], [1.0, 0.0])
    assert filt.sparse(*ok, [[5.0, 5.0]], [[0.0, 0.0]]).status == "ok"
    assert filt.sparse(*ok, [[np.nan, 5.0]], [[0.0, 0.0]]).status == "nonfinite"
    assert filt.sparse(*ok, [[5.0, 5.0]], [[0.0, np.inf]]).status == "nonfinite"
    assert filt.sparse([0.0, 0.0], [1.0, 0.0], [np.nan, 0.0], [1.0, 0.0], [], []).status == (
        "nonfinite"
    )
    bad = filt.sparse([0.0, 0.0], [1.0, 0.0], [30.0, 0.0], [np.nan, 0.0], [], [])
    assert bad.status == "nonfinite" and not bad.straight and not np.any(bad.vel_m_s)


@needs_cc
def test_c_onboard_tick_applies_the_rule_at_decisions():
    """covey_guidance_step with sparse_rule: a decided tick holds the rule's choice and filters
    it; CPolicy.command gives the same; the rule off holds the policy's velocity."""
    from firmware.cpolicy import CPolicy

    on, off = CPolicy.load(), CPolicy.load(sparse_rule=False)
    nbr, nbr_vel, nbr_h = np.array([[12.0, -10.0]]), np.array([[0.0, 1.0]]), np.array([1.57])
    args = ([0.0, 0.0], [1.0, 0.0], 0.0, GOAL, nbr, nbr_vel, nbr_h)
    r = on.onboard().step(Observation.shaped(*args), now_s=1.0)
    assert r.status == "ok" and r.decided and r.straight
    ref = safety.filter_velocity(args[0], args[1], [1.0, 0.0], nbr, nbr_vel, on.safety_cfg)
    np.testing.assert_allclose(r.vel_m_s, ref, atol=1e-5)
    np.testing.assert_allclose(on.command(*args), r.vel_m_s, atol=1e-5)
    r_off = off.onboard().step(Observation.shaped(*args), now_s=1.0)
    assert r_off.status == "ok" and not r_off.straight
    assert not np.allclose(r_off.vel_m_s, r.vel_m_s, atol=1e-3)


def test_one_vehicle_fast_path_is_the_padded_reference():
    """choose_one (Python floats, the runtime's hot path) = choose_padded (numpy, many
    vehicles) on random encounters: the same choice and the same velocity."""
    rng = np.random.default_rng(11)
    n_straight = 0
    for _ in range(400):
        k = int(rng.integers(0, 6))
        pos, vel = rng.uniform(-5, 5, 2), rng.uniform(-1, 1, 2)
        goal, asked = rng.uniform(-40, 40, 2), rng.uniform(-1, 1, 2)
        nbr_pos, nbr_vel = rng.uniform(-15, 15, (k, 2)), rng.uniform(-1, 1, (k, 2))
        one, s1 = sparse.choose_one(pos, vel, goal, asked, nbr_pos, nbr_vel, SAFE, CFG, 1.0)
        many, s2 = sparse.choose_padded(
            pos[None],
            vel[None],
            goal[None],
            asked[None],
            nbr_pos[None],
            nbr_vel[None],
            np.ones((1, k), bool),
            SAFE,
            CFG,
            1.0,
        )
        assert s1 == bool(s2[0])
        np.testing.assert_allclose(one, many[0], atol=1e-12)
        n_straight += s1
    assert 50 < n_straight < 350


@needs_cc
def test_c_rule_fuzz_under_sanitizers(capsys, fuzz_drivers):
    """covey_sparse_choose on the filter's fuzz cases (firmware/safety_cases.py: valid
    encounters and hostile copies) with a goal, itself hostile in some: every status is the
    predicted one, the output finite, zero and not straight on a fault, under ASan + UBSan and
    with the same bits as the optimised build."""
    from firmware import hostbuild
    from firmware import safety_cases as sc
    from firmware.cases import STATUS

    asan, plain = fuzz_drivers
    rng = np.random.default_rng(83)
    cases = []
    for k in range(3000):
        c = sc.random_case(rng, n_nbrs=None if k % 20 == 0 else int(rng.integers(0, 5)))
        c = c if k < 600 else sc.mutate(c, rng)
        goal = tuple(float(g) for g in np.float32(rng.uniform(-60, 60, 2)))
        if k % 7 == 0:
            goal = (float(rng.choice(sc.BAD)), goal[1])
        cases.append((c, goal))
    text = "\n".join(sc.sparse_line(c, g) for c, g in cases) + "\n"
    lines, stderr = hostbuild.run_driver(asan, text)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr[-2000:]
    assert len(lines) == len(cases)
    assert hostbuild.run_driver(plain, text)[0] == lines
    counts = dict.fromkeys(STATUS, 0)
    n_straight = 0
    for (c, goal), out_line in zip(cases, lines, strict=True):
        out = sc.parse_sparse_output(out_line)
        expect = sc.expected_sparse_status(c, goal)
        assert out["status"] == expect, (out_line, c, goal)
        counts[next(k for k, v in STATUS.items() if v == expect)] += 1
        assert np.all(np.isfinite(out["vel"]))
        if expect == STATUS["ok"]:
            n_straight += out["straight"]
            if not out["straight"]:  # the policy's velocity, untouched
                np.testing.assert_array_equal(np.float32(out["vel"]), np.float32(c.pref))
        else:
            assert not np.any(out["vel"]) and not out["straight"]
    assert counts["ok"] >= 600 and counts["nonfinite"] > 300 and counts["range"] > 300
    assert n_straight > 50
    with capsys.disabled():
        print(f"\n[C sparse fuzz] {len(cases)} inputs under ASan+UBSan: statuses {counts}, clean")
