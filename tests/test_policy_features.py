"""policy.features against a naive loop written straight from docs/POLICY_SPEC.md."""

import math

import numpy as np
import pytest

from policy import features
from policy.features import ObsConfig

CONFIGS = [
    ObsConfig(),
    ObsConfig("sincos", "closest_last", 10.0, 20.0),
    ObsConfig("paper", "closest_last", 1.0, 0.0),
    ObsConfig("sincos", "index", 3.0, 15.0),
]


def wrap(a):
    while a >= math.pi:
        a -= 2 * math.pi
    while a < -math.pi:
        a += 2 * math.pi
    return a


def naive_observe(pos, h, goal, nbr_pos, nbr_h, cfg, max_nbr=None):
    rows = []
    for j, (p, hj) in enumerate(zip(nbr_pos, nbr_h, strict=True)):
        d = math.hypot(p[0] - pos[0], p[1] - pos[1])
        if cfg.sense_range > 0 and d > cfg.sense_range:
            continue
        psi_ij = wrap(math.atan2(p[1] - pos[1], p[0] - pos[0]) - h)
        psi_ji = wrap(hj - math.atan2(pos[1] - p[1], pos[0] - p[0]))
        rows.append((d, j, psi_ij, psi_ji))
    if max_nbr is not None:
        rows = sorted(rows, key=lambda r: (r[0], r[1]))[:max_nbr]
        rows = sorted(rows, key=lambda r: r[1])
    if cfg.order == "closest_last":
        rows = sorted(rows, key=lambda r: (-r[0], r[1]))
    seq = []
    for d, _, a, b in rows:
        if cfg.encoding == "paper":
            seq.append([d / cfg.dist_scale, a, abs(b)])
        else:
            seq.append([d / cfg.dist_scale, math.sin(a), math.cos(a), math.sin(b), math.cos(b)])
    psi_d = wrap(math.atan2(goal[1] - pos[1], goal[0] - pos[0]) - h)
    g = [psi_d] if cfg.encoding == "paper" else [math.sin(psi_d), math.cos(psi_d)]
    return np.array(seq).reshape(-1, cfg.input_size), np.array(g), [r[1] for r in rows]


@pytest.mark.parametrize("cfg", CONFIGS)
@pytest.mark.parametrize("max_nbr", [None, 3])
def test_observe_matches_naive_loop(cfg, max_nbr):
    rng = np.random.default_rng(1)
    for _ in range(30):
        k = int(rng.integers(0, 12))
        pos, goal = rng.uniform(-20, 20, 2), rng.uniform(-40, 40, 2)
        nbr = rng.uniform(-25, 25, (k, 2))
        h, nh = rng.uniform(-4, 4), rng.uniform(-4, 4, k)
        seq, g, idx = features.observe(pos, h, goal, nbr, nh, cfg, max_nbr)
        seq_n, g_n, idx_n = naive_observe(pos, h, goal, nbr, nh, cfg, max_nbr)
        assert list(idx) == idx_n
        np.testing.assert_allclose(seq, seq_n, atol=1e-12)
        np.testing.assert_allclose(g, g_n, atol=1e-12)


@pytest.mark.parametrize("cfg", CONFIGS)
@pytest.mark.parametrize(("n", "max_nbr"), [(6, None), (9, 4), (120, 10)])
def test_batch_matches_single(cfg, n, max_nbr):
    rng = np.random.default_rng(n)
    size = 40 if n < 100 else 150
    pos, goal = rng.uniform(0, size, (n, 2)), rng.uniform(0, size, (n, 2))
    h = rng.uniform(-4, 4, n)
    active = rng.random(n) > 0.2
    seq, lengths, g, nbr = features.observe_batch(pos, h, goal, active, cfg, max_nbr)
    for i in np.flatnonzero(active):
        others = np.flatnonzero(active & (np.arange(n) != i))
        s1, g1, idx = features.observe(pos[i], h[i], goal[i], pos[others], h[others], cfg, max_nbr)
        assert lengths[i] == len(idx)
        np.testing.assert_array_equal(nbr[i, : lengths[i]], others[idx])
        np.testing.assert_allclose(seq[i, : lengths[i]], s1, atol=1e-12)
        assert np.all(seq[i, lengths[i] :] == 0)
        np.testing.assert_allclose(g[i], g1, atol=1e-12)
    assert np.all(lengths[~active] == 0)


def test_batch_leading_dims_are_separate_worlds():
    rng = np.random.default_rng(3)
    cfg = CONFIGS[1]
    pos, goal, h = (
        rng.uniform(0, 30, (4, 5, 2)),
        rng.uniform(0, 30, (4, 5, 2)),
        rng.uniform(-3, 3, (4, 5)),
    )
    active = rng.random((4, 5)) > 0.3
    seq, lengths, g, _ = features.observe_batch(pos, h, goal, active, cfg)
    for e in range(4):
        s, ln, gg, _ = features.observe_batch(pos[e], h[e], goal[e], active[e], cfg)
        np.testing.assert_array_equal(seq[e], s)
        np.testing.assert_array_equal(lengths[e], ln)


def test_wrap_and_rotation():
    assert features.wrap_rad(math.pi) == pytest.approx(-math.pi)
    assert features.wrap_rad(-math.pi) == pytest.approx(-math.pi)
    assert features.wrap_rad(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    # heading east (pi/2): forward is east, right is south
    np.testing.assert_allclose(features.action_to_velocity([1, 0], math.pi / 2), [0, 1], atol=1e-12)
    np.testing.assert_allclose(
        features.action_to_velocity([0, 1], math.pi / 2), [-1, 0], atol=1e-12
    )
    a = np.array([0.3, -0.7])
    np.testing.assert_allclose(
        features.velocity_to_action(features.action_to_velocity(a, 1.1), 1.1), a
    )
    np.testing.assert_allclose(features.clip_unit([3.0, 4.0]), [0.6, 0.8])


def test_config_validation():
    with pytest.raises(ValueError, match="encoding"):
        ObsConfig(encoding="polar")
    with pytest.raises(ValueError, match="order"):
        ObsConfig(order="random")
    with pytest.raises(ValueError, match="dist_scale"):
        ObsConfig(dist_scale=0.0)


@pytest.mark.parametrize("cfg", CONFIGS)
def test_padded_views_match_single(cfg):
    rng = np.random.default_rng(7)
    n, k = 8, 6
    pos, goal, h = rng.uniform(0, 40, (n, 2)), rng.uniform(0, 40, (n, 2)), rng.uniform(-3, 3, n)
    nbr, nh = rng.uniform(0, 40, (n, k, 2)), rng.uniform(-3, 3, (n, k))
    valid = rng.random((n, k)) > 0.3
    seq, lengths, g, sel = features.observe_padded(pos, h, goal, nbr, nh, valid, cfg, 4)
    for i in range(n):
        cols = np.flatnonzero(valid[i])
        s1, g1, idx = features.observe(pos[i], h[i], goal[i], nbr[i, cols], nh[i, cols], cfg, 4)
        assert lengths[i] == len(idx)
        np.testing.assert_array_equal(sel[i, : lengths[i]], cols[idx])
        np.testing.assert_allclose(seq[i, : lengths[i]], s1, atol=1e-12)
        np.testing.assert_allclose(g[i], g1, atol=1e-12)
