"""Keep-out zones in the separation filter: ORCA's obstacle half-planes (policy/zone_lines.py)
and their C twin (firmware/covey_zones.c), parity tested on random convex and concave scenes,
and flown in closed loop: the filter never commands a velocity that enters a zone, with or
without a crowd pushing towards it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import shapely

from policy import safety
from policy.zone_lines import MAX_ZONE_EDGES, ZoneSet

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")

RADIUS_M = float(np.float32(1.8))
"""The filter's zone radius at 3 m (policy.zone_lines), as the C core reads it (float32)."""
PARITY_TOL = 1e-6
"""Max |C - numpy| per component of a velocity, m/s at 1 m/s (the C output is float32)."""


@pytest.fixture(scope="module")
def lib():
    from firmware.cpolicy import load_library

    return load_library()


def _f32(x) -> np.ndarray:
    """Values both sides read the same: float32-representable float64."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def random_polygon(rng, centre_box_m=8.0) -> np.ndarray:
    """A simple star-shaped polygon (angular gaps under pi), concave about half the time."""
    while True:
        k = int(rng.integers(3, 10))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        if np.max(np.diff(np.r_[ang, ang[0] + 2 * np.pi])) >= 0.9 * np.pi:
            continue
        rad = rng.uniform(2.0, 9.0, k)
        c = rng.uniform(-centre_box_m, centre_box_m, 2)
        p = _f32(c + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1))
        if shapely.Polygon(p).is_valid and shapely.Polygon(p).area > 1.0:
            return p


def random_scene(rng):
    polys = [random_polygon(rng)]
    if rng.random() < 0.5:
        q = _f32(random_polygon(rng) + rng.choice([-1, 1], 2) * 12.0)
        if not shapely.Polygon(q).intersects(shapely.Polygon(polys[0])):
            polys.append(q)
    return polys


def test_lines_and_filter_match_c_on_random_scenes(lib):
    from firmware.czones import CZones

    rng = np.random.default_rng(35)
    cfg = safety.SafetyConfig()
    n_lines = n_changed = n_concave = 0
    worst = 0.0
    for _ in range(300):
        polys = random_scene(rng)
        n_concave += any(
            not shapely.Polygon(p).convex_hull.equals(shapely.Polygon(p)) for p in polys
        )
        zs = ZoneSet.of(polys, RADIUS_M)
        cz = CZones(lib, polys, RADIUS_M)
        union = shapely.union_all([shapely.Polygon(p) for p in polys])
        for _ in range(10):
            pos = _f32(rng.uniform(-20, 20, 2))
            if union.distance(shapely.Point(pos)) < 0.05:
                continue  # on an edge: a sign flip away from the other side (both are right)
            vel = _f32(rng.uniform(-1, 1, 2))
            pref = _f32(rng.uniform(-1.2, 1.2, 2))
            sigma = float(rng.choice([0.0, 0.0, 0.5]))  # padded by sigma_k x the own 1-sigma
            pad = float(np.float32(cfg.sigma_k * sigma))
            ref_lines = zs.lines(pos, vel, cfg.max_speed_m_s, pad)
            c_lines = cz.lines(pos, vel, cfg.max_speed_m_s, pad)
            assert len(ref_lines) == len(c_lines)
            for (p, d), (q, e) in zip(ref_lines, c_lines, strict=True):
                np.testing.assert_allclose(p, q, atol=1e-9)
                np.testing.assert_allclose(d, e, atol=1e-9)
            n_lines += len(ref_lines)
            k = int(rng.integers(0, 5))
            nbr_pos = _f32(pos + rng.uniform(-8, 8, (k, 2)))
            nbr_vel = _f32(rng.uniform(-1, 1, (k, 2)))
            ref = safety.filter_one(
                pos, vel, pref, nbr_pos, nbr_vel, cfg, pos_sigma_m=sigma, zones=zs
            )
            r = cz.evaluate(cfg, pos, vel, pref, nbr_pos, nbr_vel, pos_sigma_m=sigma)
            assert r.status == "ok"
            c_v = r.vel_m_s
            worst = max(worst, float(np.abs(ref - c_v).max()))
            n_changed += not np.allclose(ref, safety._clip_speed(pref, 1.0))
    assert worst <= PARITY_TOL, worst
    assert n_lines > 500 and n_changed > 300 and n_concave > 50  # the cases exercise it


def test_no_zones_is_exactly_the_filter(lib):
    from firmware.csafety import CSafetyFilter
    from firmware.czones import CZones

    cfg = safety.SafetyConfig()
    far = [np.array([[1000.0, 1000.0], [1010.0, 1000.0], [1010.0, 1010.0]])]
    cz = CZones(lib, far, RADIUS_M)
    plain = CSafetyFilter(lib, cfg)
    rng = np.random.default_rng(5)
    for _ in range(50):
        pos, vel, pref = _f32(rng.uniform(-5, 5, (3, 2)))
        nbr = _f32(rng.uniform(-6, 6, (3, 2)))
        nv = _f32(rng.uniform(-1, 1, (3, 2)))
        assert np.array_equal(
            cz.filter(cfg, pos, vel, pref, nbr, nv), plain(pos, vel, pref, nbr, nv)
        )
        assert np.array_equal(
            safety.filter_one(pos, vel, pref, nbr, nv, cfg, zones=ZoneSet.of(far, RADIUS_M)),
            safety.filter_one(pos, vel, pref, nbr, nv, cfg),
        )


def _fly(step_fn, polys, rng, n_steps=400, dt_s=0.1, crowd=False):
    """Closed loop on an ideal point mass aimed through the zones; the closest true distance."""
    union = shapely.union_all([shapely.Polygon(p) for p in polys])
    while True:
        pos = rng.uniform(-25, 25, 2)
        if union.distance(shapely.Point(pos)) > RADIUS_M + 0.5:
            break
    goal = -pos
    vel = np.zeros(2)
    closest = np.inf
    for _ in range(n_steps):
        d = goal - pos
        pref = d / max(np.hypot(*d), 1e-9)
        if crowd:  # three vehicles flying at us from the side away from the zones
            away = pos - np.array(union.centroid.coords[0])
            away /= max(np.hypot(*away), 1e-9)
            nbr_pos = pos + away * 3.7 + np.array([[0, 0], [1.5, -1.5], [-1.5, 1.5]])
            nbr_vel = np.broadcast_to(-away, (3, 2))
        else:
            nbr_pos, nbr_vel = np.zeros((0, 2)), np.zeros((0, 2))
        vel = step_fn(_f32(pos), _f32(vel), _f32(pref), _f32(nbr_pos), _f32(nbr_vel))
        pos = pos + vel * dt_s
        closest = min(closest, union.distance(shapely.Point(pos)))
    return closest


@pytest.mark.parametrize("crowd", [False, True])
def test_the_filter_never_enters_a_zone_numpy_and_c(lib, crowd):
    from firmware.czones import CZones

    cfg = safety.SafetyConfig()
    rng = np.random.default_rng(7 + crowd)
    closest = {"numpy": np.inf, "c": np.inf}
    for _ in range(12):
        polys = random_scene(rng)
        zs = ZoneSet.of(polys, RADIUS_M)
        cz = CZones(lib, polys, RADIUS_M)
        seed = int(rng.integers(1 << 30))

        def ref(p, v, pref, np_, nv, zs=zs):
            return safety.filter_one(p, v, pref, np_, nv, cfg, zones=zs)

        def c(p, v, pref, np_, nv, cz=cz):
            return cz.filter(cfg, p, v, pref, np_, nv)

        for name, fn in (("numpy", ref), ("c", c)):
            got = _fly(fn, polys, np.random.default_rng(seed), crowd=crowd)
            closest[name] = min(closest[name], got)
    # the discrete step and float32 inputs cost micrometres, never the radius
    assert closest["numpy"] >= RADIUS_M - 1e-3, closest
    assert closest["c"] >= RADIUS_M - 1e-3, closest


def test_without_zone_lines_a_vehicle_flies_straight_in():
    """The check above can fail: the same flight without the zones' lines enters."""
    cfg = safety.SafetyConfig()
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    pos, v = np.array([-10.0, 5.0]), np.zeros(2)
    for _ in range(200):
        v = safety.filter_one(pos, v, np.array([1.0, 0.0]), np.zeros((0, 2)), np.zeros((0, 2)), cfg)
        pos = pos + 0.1 * v
    assert shapely.Polygon(sq).contains(shapely.Point(pos))


def test_c_refuses_bad_polygons(lib):
    from firmware.czones import CZones

    with pytest.raises(ValueError, match="range"):
        CZones(lib, [np.array([[0, 0], [10, 10], [10, 0], [0, 12]], float)], RADIUS_M)  # a bow tie
    with pytest.raises(ValueError, match="range"):
        CZones(lib, [np.array([[0, 0], [1, 0]], float)], RADIUS_M)
    with pytest.raises(ValueError, match="nonfinite"):
        CZones(lib, [np.array([[0, 0], [np.nan, 0], [1, 1]], float)], RADIUS_M)
    with pytest.raises(ValueError, match="range"):
        CZones(lib, [np.array([[0, 0], [0, 0], [1, 0], [1, 1]], float)], RADIUS_M)  # repeated
    with pytest.raises(ValueError, match="crosses itself"):
        ZoneSet.of([np.array([[0, 0], [10, 10], [10, 0], [0, 12]], float)], RADIUS_M)


def test_many_edges_are_capped_to_the_nearest(lib):
    """A 200-vertex circle next to the vehicle: both sides keep the same 32 nearest edges."""
    from firmware.czones import CZones

    ang = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = _f32(np.stack([5 * np.cos(ang), 5 * np.sin(ang)], 1))
    zs = ZoneSet.of([circle], RADIUS_M)
    cz = CZones(lib, [circle], RADIUS_M)
    pos, vel = _f32([7.5, 0.0]), _f32([-1.0, 0.0])
    assert len(zs.nearby_edges(pos, 1.0)) == MAX_ZONE_EDGES
    ref, c = zs.lines(pos, vel, 1.0), cz.lines(pos, vel, 1.0)
    assert len(ref) == len(c) > 0
    np.testing.assert_allclose(np.array(ref), np.array(c), atol=1e-9)


def test_a_vehicle_inside_the_radius_is_pushed_out_against_a_gust(lib):
    """RVO2 only forbids approaching an edge; a gust the velocity loop does not reject would
    carry a vehicle in. The zone lines ask for (radius - distance) / 1 s outwards instead."""
    from firmware.czones import CZones

    cfg = safety.SafetyConfig()
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    zs, cz = ZoneSet.of([sq], RADIUS_M), CZones(lib, [sq], RADIUS_M)
    for name, step in (
        (
            "numpy",
            lambda p, v: safety.filter_one(
                p, v, np.zeros(2), np.zeros((0, 2)), np.zeros((0, 2)), cfg, zones=zs
            ),
        ),
        ("c", lambda p, v: cz.filter(cfg, p, v, np.zeros(2), np.zeros((0, 2)), np.zeros((0, 2)))),
    ):
        pos, v = np.array([-1.0, 5.0]), np.zeros(2)  # 1 m off the west edge, radius 1.8
        gust = np.array([0.2, 0.0])  # towards the zone, never rejected
        for _ in range(100):
            v = step(_f32(pos), _f32(v))
            pos = pos + 0.1 * (v + gust)
        assert -pos[0] >= RADIUS_M - 0.25, (name, pos)  # held off against the gust
        assert v[0] < 0.0, name


def test_padded_rows_equal_the_one_vehicle_path():
    """filter_padded (fleet-sim, covey eval) with zones = filter_one row by row."""
    cfg = safety.SafetyConfig()
    rng = np.random.default_rng(3)
    polys = [random_polygon(rng) for _ in range(2)]
    zs = ZoneSet.of(polys, RADIUS_M)
    n, k = 60, 4
    pos = rng.uniform(-20, 20, (n, 2))
    vel = rng.uniform(-1, 1, (n, 2))
    # within the speed disc: filter_padded clips the preference first, filter_one optimises
    # towards the unclipped one (they differ there with or without zones)
    pref = rng.uniform(-0.7, 0.7, (n, 2))
    nbr_pos = pos[:, None] + rng.uniform(-6, 6, (n, k, 2))
    nbr_vel = rng.uniform(-1, 1, (n, k, 2))
    valid = rng.random((n, k)) < 0.7
    sig = rng.choice([0.0, 0.5], n)
    got = safety.filter_padded(
        pos, vel, pref, nbr_pos, nbr_vel, valid, cfg, pos_sigma_m=sig, zones=zs
    )
    for i in range(n):
        m = valid[i]
        ref = safety.filter_one(
            pos[i], vel[i], pref[i], nbr_pos[i, m], nbr_vel[i, m], cfg, pos_sigma_m=sig[i], zones=zs
        )
        np.testing.assert_allclose(got[i], ref, atol=1e-9, err_msg=str(i))


def _case_tokens(polys, fence: bool, own, pref, radius=1.8, horizon=2.0) -> list:
    flat = [f"{v:.9g}" for p in polys for v in np.asarray(p, np.float32).ravel()]
    return [
        str(len(polys)),
        str(int(fence)),
        f"{radius:.9g}",
        f"{horizon:.9g}",
        str(len(polys)),
        *[str(len(p)) for p in polys],
        str(len(flat)),
        *flat,
        *[f"{v:.9g}" for v in own],
        *[f"{v:.9g}" for v in pref],
    ]


def test_zones_fuzz_under_asan_and_ubsan():
    """covey_zones_init and covey_safety_filter_zones on valid scenes and on hostile mutations
    (NaN, inf, huge, negative and oversized counts, a count that disagrees with the vertices),
    built with ASan + UBSan: exactly the predicted status where one is predicted, never a crash,
    and the output inside the speed disc."""
    from firmware import hostbuild

    driver = hostbuild.build_zones_driver(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    rng = np.random.default_rng(99)
    lines, want = [], []
    fence = np.array([[-60, -60], [60, -60], [60, 60], [-60, 60]], float)
    for i in range(300):
        polys = random_scene(rng)
        with_fence = i % 3 == 0
        if with_fence:
            polys = [*polys, fence]
        own = [*rng.uniform(-20, 20, 2), *rng.uniform(-1, 1, 2), float(rng.choice([0.0, 0.5]))]
        pref = rng.uniform(-1.5, 1.5, 2)
        tokens = _case_tokens(polys, with_fence, own, pref)
        lines.append(" ".join(tokens))
        want.append("valid")
        n_head = 5 + len(polys)  # n_polygons .. counts
        n_flat = int(tokens[n_head])
        targeted = [
            (n_head + 1 + int(rng.integers(n_flat)), "nan", "2"),  # a vertex
            (n_head + 1 + int(rng.integers(n_flat)), "-inf", "2"),
            (n_head + 1 + int(rng.integers(n_flat)), "3e6", "3"),  # beyond the position range
            (5, "2", "3"),  # a polygon of 2 vertices
            (0, "-1", "3"),  # n_polygons
            (0, "65", "3"),
            (1, "2", "3"),  # has_fence
            (2, "0", "3"),  # radius
            (2, "nan", "2"),
            (3, "1e9", "3"),  # horizon
        ]
        for pos, value, status in targeted:
            mutated = list(tokens)
            mutated[pos] = value
            lines.append(" ".join(mutated))
            want.append(status)
        for _ in range(8):  # anything at all in any numeric slot but the framing
            mutated = list(tokens)
            ints = [0, 1, *range(5, n_head)]  # n_polygons, has_fence, the counts
            floats = [2, 3, *range(n_head + 1, len(tokens))]
            for _ in range(int(rng.integers(1, 4))):
                if rng.random() < 0.3:
                    mutated[int(rng.choice(ints))] = str(
                        rng.choice(["-1", "0", "2", "7", "65", "100000", "-2147483648"])
                    )
                else:
                    mutated[int(rng.choice(floats))] = str(
                        rng.choice(["nan", "inf", "-inf", "0", "-1", "1e30", "-3e38", "1e-40"])
                    )
            lines.append(" ".join(mutated))
            want.append("any")
    out, _ = hostbuild.run_driver(driver, "\n".join(lines) + "\n")
    assert len(out) == len(lines)
    seen: dict = {}
    for got, w in zip(out, want, strict=True):
        init, filt, *rest = got.split()
        seen[init] = seen.get(init, 0) + 1
        if w == "valid":
            assert init == "0" and filt == "0", got
        elif w != "any":
            assert init == w, (got, w)
        assert init in {"0", "2", "3"}, got
        if init == "0" and filt == "0":
            vn, ve = float(rest[0]), float(rest[1])
            assert np.hypot(vn, ve) <= 1.0 + 1e-6, got
    print(f"[zones fuzz] {len(lines)} inputs under ASan+UBSan: init statuses {seen}, clean")


def test_c_and_numpy_keep_the_same_sigma_padded_clearance(lib):
    """With a position 1-sigma the zone lines move out by sigma_k x sigma on both sides: a vehicle
    inside the padded radius but outside the bare one is pushed out by both, alike within 1e-6
    (and not at all with sigma 0: the padding is what pushes)."""
    from firmware.czones import CZones
    from policy.zone_lines import ZONE_MAX_PUSH_SHARE, ZONE_RECOVER_S

    cfg = safety.SafetyConfig()
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    zs, cz = ZoneSet.of([sq], RADIUS_M), CZones(lib, [sq], RADIUS_M)
    none = np.zeros((0, 2))
    pref = _f32([0.0, 1.0])  # along the west edge (north = 0 .. 10 at east = 0 .. 10)
    for sigma in (0.25, 0.5, 0.8):
        padded = RADIUS_M + cfg.sigma_k * sigma
        for off in np.linspace(RADIUS_M + 0.05, padded - 0.05, 5):
            pos, vel = _f32([-off, 5.0]), _f32([0.0, 0.5])
            ref = safety.filter_one(pos, vel, pref, none, none, cfg, pos_sigma_m=sigma, zones=zs)
            c = cz.evaluate(cfg, pos, vel, pref, none, none, pos_sigma_m=sigma)
            assert c.status == "ok"
            np.testing.assert_allclose(c.vel_m_s, ref, atol=PARITY_TOL)
            want = min((padded - off) / ZONE_RECOVER_S, ZONE_MAX_PUSH_SHARE * cfg.max_speed_m_s)
            assert -ref[0] >= want - 1e-5, (sigma, off, ref)  # away from the edge (north < 0)
            bare = safety.filter_one(pos, vel, pref, none, none, cfg, pos_sigma_m=0.0, zones=zs)
            c0 = cz.evaluate(cfg, pos, vel, pref, none, none, pos_sigma_m=0.0).vel_m_s
            np.testing.assert_allclose(c0, bare, atol=PARITY_TOL)
            assert abs(bare[0]) < 1e-6  # outside the bare radius: flies along the edge


def test_a_deep_vehicle_beats_a_two_sigma_gust(lib):
    """A realistic vehicle's gust (0.2 m/s 1-sigma) at 3 sigma, towards the zone, never
    rejected: the recovery push still holds the vehicle within gust x ZONE_RECOVER_S of the
    radius (numpy and C); the first push (1 s, at most half the speed) let it sink on (seed 11:
    1.4 m into the padded radius)."""
    from firmware.czones import CZones
    from policy.zone_lines import ZONE_RECOVER_S

    cfg = safety.SafetyConfig()
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    zs, cz = ZoneSet.of([sq], RADIUS_M), CZones(lib, [sq], RADIUS_M)
    none = np.zeros((0, 2))
    pref = np.array([0.0, 1.0])  # along the south edge (north 0, east 0 .. 10) at full speed
    gust = np.array([0.6, 0.0])  # north: into the zone
    for name, step in (
        ("numpy", lambda p, v: safety.filter_one(p, v, pref, none, none, cfg, zones=zs)),
        ("c", lambda p, v: cz.filter(cfg, p, v, pref, none, none)),
    ):
        pos, v = np.array([-RADIUS_M, 0.5]), np.zeros(2)
        worst = np.inf
        for _ in range(90):  # 9 s: along the 10 m edge
            v = step(_f32(pos), _f32(v + gust))
            pos = pos + 0.1 * (v + gust)
            worst = min(worst, shapely.Polygon(sq).distance(shapely.Point(pos)))
        assert worst >= RADIUS_M - gust[0] * ZONE_RECOVER_S - 0.1, (name, worst)
