"""Guidance decides at the policy's trained period and holds in between; the filter runs every tick."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from agent.guidance import Guidance, GuidanceConfig, NeighbourViews
from agent.neighbours import NeighbourSnapshot
from comms.scope import ScopeConfig
from policy.runtime import FILTERED_BERTH_SHARE, GuidancePolicy

GOAL = np.array([20.0, 0.0, -5.0])


def snapshot(pos_ne_m=(), vel_ne_m_s=(), heading_rad=None) -> NeighbourSnapshot:
    k = len(pos_ne_m)
    return NeighbourSnapshot(
        pos_ned_m=np.array([[*p, -5.0] for p in pos_ne_m]).reshape(k, 3),
        vel_ned_m_s=np.array([[*v, 0.0] for v in vel_ne_m_s]).reshape(k, 3),
        heading_rad=np.zeros(k) if heading_rad is None else np.asarray(heading_rad, float),
        ids=tuple(range(2, 2 + k)),
        age_s=np.zeros(k),
        stale_ids=(),
    )


def fly(g: Guidance, ticks: int, nbrs: NeighbourSnapshot, dt_s: float = 0.1):
    """Point-mass loop at 10 Hz; returns (outputs, positions)."""
    pos, vel, heading = np.array([0.0, 0.0, -5.0]), np.zeros(3), 0.0
    outs, track = [], []
    for k in range(ticks):
        out = g.goto(pos, vel, heading, GOAL, nbrs, now_s=k * dt_s)
        vel, heading = out.vel_ned_m_s, out.heading_rad
        pos = pos + vel * dt_s
        outs.append(out)
        track.append(pos.copy())
    return outs, np.array(track)


def test_decides_once_per_period_and_holds_in_between():
    g = Guidance(GuidanceConfig())
    assert g.decision_period_s == pytest.approx(g.policy.decision_period_s) == pytest.approx(1.0)
    outs, _ = fly(g, 35, snapshot())
    decided = [k for k, o in enumerate(outs) if o.decided]
    assert decided == [0, 10, 20, 30]
    for k in range(1, 10):  # no neighbours, no filter: exactly the held velocity
        np.testing.assert_array_equal(outs[k].vel_ned_m_s[:2], outs[0].vel_ned_m_s[:2])


def test_every_tick_when_configured_or_without_a_clock():
    g = Guidance(GuidanceConfig(decision_period_s=0.0))
    outs, _ = fly(g, 5, snapshot())
    assert all(o.decided for o in outs)
    g = Guidance(GuidanceConfig())
    pos, vel = np.array([0.0, 0.0, -5.0]), np.zeros(3)
    assert all(g.goto(pos, vel, 0.0, GOAL, snapshot()).decided for _ in range(3))


def test_new_goal_or_a_hold_forces_a_decision():
    g = Guidance(GuidanceConfig())
    pos, vel, nb = np.array([0.0, 0.0, -5.0]), np.zeros(3), snapshot()
    assert g.goto(pos, vel, 0.0, GOAL, nb, now_s=0.0).decided
    assert not g.goto(pos, vel, 0.0, GOAL, nb, now_s=0.1).decided
    assert g.goto(pos, vel, 0.0, GOAL + [0.0, 5.0, 0.0], nb, now_s=0.2).decided  # new goal
    g.hold(pos, vel, 0.0, pos, nb)
    assert g.goto(pos, vel, 0.0, GOAL, nb, now_s=0.3).decided  # after a hold
    assert not g.goto(pos, vel, 0.0, GOAL, nb, now_s=0.4, decide=False).decided
    assert g.goto(pos, vel, 0.0, GOAL, nb, now_s=0.5, decide=True).decided


def test_filter_acts_on_held_ticks():
    """A neighbour head-on: the held policy velocity still goes through the filter every tick."""
    g = Guidance(GuidanceConfig())
    pos, vel = np.array([0.0, 0.0, -5.0]), np.array([1.0, 0.0, 0.0])
    g.goto(pos, vel, 0.0, GOAL, snapshot(), now_s=0.0)  # decided with nobody around
    out = g.goto(pos, vel, 0.0, GOAL, snapshot([(4.0, 0.0)], [(-1.0, 0.0)]), now_s=0.1)
    assert not out.decided and out.filtered


def _mean_acc(outs) -> float:
    v = np.array([o.vel_ned_m_s[:2] for o in outs])
    return float(np.mean(np.linalg.norm(np.diff(v, axis=0), axis=1)) / 0.1)


def test_arrives_smoothly():
    """Held decisions give the smooth tracks of training (docs/policy.md: about 0.2 m/s^2);
    with the sparse rule (the default) a lone vehicle flies straight and stops on its goal."""
    policy = GuidanceConfig(sparse_rule=False)
    outs, track = fly(Guidance(policy), 400, snapshot())
    assert math.dist(track[-1][:2], GOAL[:2]) < 1.5
    every_tick, _ = fly(Guidance(replace(policy, decision_period_s=0.0)), 400, snapshot())
    mean_acc, mean_acc_tick = _mean_acc(outs), _mean_acc(every_tick)
    ruled, ruled_track = fly(Guidance(GuidanceConfig()), 400, snapshot())
    print(
        f"mean |accel| held {mean_acc:.3f} m/s^2, every tick {mean_acc_tick:.3f} m/s^2, "
        f"sparse rule {_mean_acc(ruled):.3f} m/s^2"
    )
    assert mean_acc <= mean_acc_tick
    assert math.dist(ruled_track[-1][:2], GOAL[:2]) < 0.05
    assert np.abs(ruled_track[:, 1]).max() < 1e-9  # straight along the line to the goal
    assert _mean_acc(ruled) <= mean_acc


def test_bad_period_is_refused():
    for bad in (-1.0, math.nan, 11.0):
        with pytest.raises(ValueError, match="decision_period_s"):
            GuidanceConfig(decision_period_s=bad)


def test_the_policy_is_told_a_narrower_berth_and_the_filter_keeps_the_separation():
    """policy_separation_m: the network's distance scale, not the filter's radius (nor the
    decision period). Default with the filter: a share of the separation; without: all of it."""
    told = {
        GuidanceConfig(): 3.0 * FILTERED_BERTH_SHARE,
        GuidanceConfig(separation_m=6.0): 6.0 * FILTERED_BERTH_SHARE,
        GuidanceConfig(safety_filter=False): 3.0,
        GuidanceConfig(policy_separation_m=2.0): 2.0,
        GuidanceConfig(policy_separation_m=2.0, safety_filter=False): 2.0,
    }
    for cfg, told_m in told.items():
        g = Guidance(cfg)
        assert cfg.told_separation_m == pytest.approx(told_m)
        assert g.policy.dist_scale_m == pytest.approx(told_m / 3.0)
        assert g.safety_cfg.radius_m == cfg.separation_m
        assert g.decision_period_s == pytest.approx(cfg.separation_m / 3.0)
    # what the network decides is what a policy told 1 m decides, not one told 3 m
    pos, vel = np.array([0.0, 0.0, -5.0]), np.array([1.0, 0.0, 0.0])
    nbrs = snapshot([(8.0, 0.5)], [(-1.0, 0.0)], [math.pi])  # head-on, 8 m ahead
    out = Guidance(GuidanceConfig(safety_filter=False)).goto(pos, vel, 0.0, GOAL, nbrs, now_s=0.0)
    narrow = Guidance(GuidanceConfig(policy_separation_m=1.0, safety_filter=False))
    held = narrow.goto(pos, vel, 0.0, GOAL, nbrs, now_s=0.0).vel_ned_m_s[:2]
    args = (pos[:2], vel[:2], 0.0, GOAL[:2], [[8.0, 0.5]], [[-1.0, 0.0]], [math.pi])
    told_1m = GuidancePolicy.load(separation_m=3.0, policy_separation_m=1.0, safety_filter=False)
    np.testing.assert_allclose(held, told_1m.command(*args), atol=1e-12)
    # told 3 m it turns away early (east velocity -0.50 m/s); told 1 m it keeps on (-0.18)
    assert held[1] > out.vel_ned_m_s[1] + 0.2


def test_the_policys_berth_does_not_narrow_what_guidance_hears():
    base = ScopeConfig()
    wide = GuidanceConfig(safety_filter=True, policy_separation_m=3.0).scope(base)
    for ps in (None, 0.5, 1.0):
        assert GuidanceConfig(policy_separation_m=ps).scope(base) == wide


def test_bad_policy_separation_is_refused():
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="policy_separation_m"):
            GuidanceConfig(policy_separation_m=bad)


@pytest.mark.parametrize("max_neighbours", [None, 0, 3, 10, 50])
def test_nearest_matches_a_plain_search(max_neighbours: int | None) -> None:
    """NeighbourViews.nearest (vectorised) against a per-row sort: the same neighbours, never
    the row itself, never an inactive entry, the stale flags carried."""
    rng = np.random.default_rng(7)
    m, k = 40, 12
    world = rng.uniform(-100.0, 100.0, (m, 3))
    vel = rng.normal(size=(m, 3))
    heading = rng.uniform(-math.pi, math.pi, m)
    active = rng.random(m) > 0.2
    stale = rng.random(m) > 0.7
    self_index = np.concatenate([np.arange(k - 2), [-1, -1]])  # two rows not in the world
    rows_pos = np.concatenate([world[: k - 2], rng.uniform(-100.0, 100.0, (2, 3))])
    views = NeighbourViews.nearest(
        rows_pos, self_index, world, vel, heading, active, stale, max_neighbours
    )
    for r in range(k):
        d2 = [
            (float(np.sum((rows_pos[r, :2] - world[j, :2]) ** 2)), j)
            for j in range(m)
            if active[j] and j != self_index[r]
        ]
        want = sorted(d2)[: m if max_neighbours is None else max_neighbours]
        pos, v, h, st = views.row(r)
        got = sorted(int(np.flatnonzero((world == p).all(axis=1))[0]) for p in pos)
        assert got == sorted(j for _, j in want)
        order = np.argsort([np.flatnonzero((world == p).all(axis=1))[0] for p in pos]).astype(int)
        idx = np.array(got, dtype=int)
        assert np.array_equal(v[order], vel[idx]) and np.array_equal(h[order], heading[idx])
        assert np.array_equal(st[order], stale[idx])


def test_goto_rows_route_around_zones_widened_by_their_own_position_sigma():
    """A row on plain GNSS flies a route that keeps the filter's padding for its sigma more from
    the zone (policy/routes.py `Router.widened`); an exact row flies the base route."""
    from agent.guidance import BatchGuidance

    square = np.array([[5.0, -5.0], [5.0, 5.0], [15.0, 5.0], [15.0, -5.0]])
    g = BatchGuidance(GuidanceConfig(), 2)
    g.set_zones([square])
    pos = np.array([[-5.0, 0.0, -5.0], [-5.0, 0.0, -5.0]])
    target = np.array([[25.0, 0.0, -5.0], [25.0, 0.0, -5.0]])
    none = np.zeros((2, 0))
    views = NeighbourViews(
        np.zeros((2, 0, 3)), np.zeros((2, 0, 3)), none, none.astype(bool), none.astype(bool),
        own_pos_sigma_m=np.array([0.0, 0.5]),
    )  # fmt: skip
    rows = np.arange(2)
    g.step(0.0, rows, pos, np.zeros((2, 3)), np.zeros(2), target, np.zeros(2, bool), views)
    pad = g.safety_cfg.sigma_k * 0.5
    router = g.router
    np.testing.assert_allclose(g.waypoint_m[0], router.next_waypoint(pos[0, :2], target[0, :2]))
    np.testing.assert_allclose(
        g.waypoint_m[1], router.next_waypoint(pos[1, :2], target[1, :2], pad)
    )
    assert np.abs(g.waypoint_m[1, 1]) > np.abs(g.waypoint_m[0, 1]) + 1.0  # wider round
