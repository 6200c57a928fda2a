"""The PX4 module's tick takes what the C core knows of the sky (firmware/px4): manned aircraft
keep their own berth (the traffic table's kinds, covey_traffic_kinds; before, the tick flattened
them to plain traffic), and the keep-out zones of the autopilot's own geofence (covey_fence.c:
MAVLink fence items, as PX4 keeps them in dataman) are hard lines of the filter
(covey_guidance_step_zones). All through the real compiled C."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from policy import safety
from policy.observation import Observation, Sky
from policy.zone_lines import ZoneSet

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")

RADIUS_M = float(np.float32(1.8))
"""The zone clearance at 3 m, 0.5 x 3 m x 1.2 (covey_zone_radius_m), as float32."""
DT_S = 0.1


@pytest.fixture(scope="module")
def lib():
    from firmware.cpolicy import load_library

    return load_library()


def _f32(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32).astype(np.float64)


C_SHAPE = _f32([[0, 0], [0, 6], [6, 6], [6, 4], [2, 4], [2, 2], [6, 2], [6, 0]])  # clockwise
SQUARE = _f32([[10, -12], [14, -12], [14, -8], [10, -8]])  # counter-clockwise
FENCE = _f32([[-40, -40], [-40, 40], [40, 40], [40, -40]])


def _circle_ring(centre, radius_m: float, inclusion: bool) -> np.ndarray:
    """comms/plan_io.py's polygon of a circle (inscribed / circumscribed 32-gon), float32."""
    r = radius_m if inclusion else radius_m / math.cos(math.pi / 32)
    a = 2 * np.pi * np.arange(32) / 32
    return _f32(np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)], 1))


def _items():
    from firmware import cfence as cf

    return [
        cf.FenceItem(cf.RETURN_POINT, 0, 1.0, 1.0),
        *cf.polygon_items(cf.POLYGON_INCLUSION, FENCE),
        *cf.polygon_items(cf.POLYGON_EXCLUSION, C_SHAPE),
        cf.FenceItem(cf.CIRCLE_EXCLUSION, 0, -15.0, 5.0, 4.0),
        *cf.polygon_items(cf.POLYGON_EXCLUSION, SQUARE),
    ]


def test_fence_items_give_the_same_zone_lines_as_the_plan_polygons(lib):
    """Polygons either way round, a circle (circumscribed 32-gon), the inclusion fence (last,
    wherever it is uploaded) and a return point (skipped): the lines equal numpy's ZoneSet of
    the same polygons at random positions."""
    from firmware.cfence import CFence

    cz = CFence(lib, _items(), safety.SafetyConfig())
    assert cz.status == "ok" and cz.radius_m == pytest.approx(RADIUS_M)
    ring = _circle_ring((-15.0, 5.0), 4.0, inclusion=False)
    zs = ZoneSet.of([C_SHAPE, ring, SQUARE], RADIUS_M, fence_m=FENCE)
    rng = np.random.default_rng(35)
    n_lines = 0
    for _ in range(400):
        box_m = 42.0 if rng.random() < 0.3 else 20.0  # the fence's edges, or the zones'
        pos, vel = _f32(rng.uniform(-box_m, box_m, 2)), _f32(rng.uniform(-1, 1, 2))
        pad = float(np.float32(rng.choice([0.0, 1.5])))
        ref, got = zs.lines(pos, vel, 1.0, pad), cz.lines(pos, vel, 1.0, pad)
        assert len(ref) == len(got)
        for (p, d), (q, e) in zip(ref, got, strict=True):
            np.testing.assert_allclose(p, q, atol=1e-6)
            np.testing.assert_allclose(d, e, atol=1e-6)
        n_lines += len(ref)
    assert n_lines > 100  # the scene is near enough to matter


def _bad_fences():
    from firmware import cfence as cf

    sq = cf.polygon_items(cf.POLYGON_EXCLUSION, SQUARE)
    return {
        "polygon cut short": (sq[:3], "range"),
        "vertex count changes": (sq[:2] + [cf.FenceItem(cf.POLYGON_EXCLUSION, 5, 1, 1)], "range"),
        "two vertices": (cf.polygon_items(cf.POLYGON_EXCLUSION, SQUARE[:2]), "range"),
        "commands mixed": (sq[:3] + cf.polygon_items(cf.POLYGON_INCLUSION, SQUARE)[:1], "range"),
        "two fences": (
            cf.polygon_items(cf.POLYGON_INCLUSION, FENCE)
            + [cf.FenceItem(cf.CIRCLE_INCLUSION, 0, 0, 0, 30.0)],
            "range",
        ),
        "circle NaN": (sq + [cf.FenceItem(cf.CIRCLE_EXCLUSION, 0, math.nan, 0, 3.0)], "nonfinite"),
        "circle radius 0": (sq + [cf.FenceItem(cf.CIRCLE_EXCLUSION, 0, 0, 0, 0.0)], "range"),
        "bow tie": (
            cf.polygon_items(cf.POLYGON_EXCLUSION, [[0, 0], [10, 10], [10, 0], [0, 10]]),
            "range",
        ),
        "vertex NaN": (
            cf.polygon_items(cf.POLYGON_EXCLUSION, [[0, 0], [0, 5], [math.nan, 5]]),
            "nonfinite",
        ),
        "too many vertices": (
            cf.polygon_items(
                cf.POLYGON_EXCLUSION, _circle_ring((0, 0), 50.0, True).repeat(17, 0)[:520]
            ),
            "range",
        ),
    }


@pytest.mark.parametrize("case", sorted(_bad_fences()))
def test_a_bad_fence_is_refused_with_its_reason_and_leaves_no_zones(lib, case):
    from firmware.cfence import CFence

    items, want = _bad_fences()[case]
    cz = CFence(lib, items, safety.SafetyConfig())
    assert cz.status == want
    assert cz.lines((12.0, -5.0), (0.0, -1.0), 1.0) == []  # next to the square: nothing kept


def test_no_fence_items_is_no_zones(lib):
    from firmware.cfence import CFence

    cz = CFence(lib, [], safety.SafetyConfig())
    assert cz.status == "ok" and cz.lines((0.0, 0.0), (1.0, 0.0), 1.0) == []


def _fly_tick(onboard, goal, n_steps, **step_kw):
    """Closed loop of one ideal vehicle from the origin through the C tick; its positions."""
    pos, vel = np.zeros(2), np.zeros(2)
    heading = math.atan2(goal[1], goal[0])
    track = [pos]
    for k in range(n_steps):
        obs = Observation.shaped(pos, vel, heading, goal, np.zeros((0, 2)), np.zeros((0, 2)), [])
        r = onboard.step(obs, k * DT_S, **step_kw)
        assert r.status == "ok"
        vel = r.vel_m_s
        if np.hypot(*vel) > 0.05:
            heading = math.atan2(vel[1], vel[0])
        pos = pos + vel * DT_S
        track.append(pos)
    return np.array(track)


def test_the_tick_keeps_out_of_the_fence_zones(lib):
    """A goal straight behind an exclusion polygon: the module's tick with the fence's zones
    never comes nearer than the clearance (1.8 m at 3 m); without them it flies in."""
    import shapely

    from firmware import cfence as cf
    from firmware.cpolicy import CPolicy

    pol = CPolicy.load(sparse_rule=False)
    block = _f32([[8, -4], [8, 4], [12, 4], [12, -4]])
    zones = cf.CFence(lib, cf.polygon_items(cf.POLYGON_EXCLUSION, block), pol.safety_cfg)
    assert zones.status == "ok"
    poly = shapely.Polygon(block)
    dist = [
        shapely.distance(
            shapely.points(_fly_tick(pol.onboard(1.0), (20.0, 0.0), 300, **kw)), poly
        ).min()
        for kw in ({"zones": zones}, {})
    ]
    assert dist[0] >= RADIUS_M - 0.02 and dist[1] == 0.0


def test_the_tick_filters_with_the_zones_as_numpy_does(lib):
    """At a decision the tick's output is the numpy filter's (policy.safety.filter_one with the
    same zones) of the held velocity, with neighbours, uncertainty and traffic."""
    from firmware import cfence as cf
    from firmware.cpolicy import CPolicy

    pol = CPolicy.load(sparse_rule=False)
    cfg = pol.safety_cfg
    zones = cf.CFence(lib, _items(), cfg)
    zs = ZoneSet.of(
        [C_SHAPE, _circle_ring((-15.0, 5.0), 4.0, False), SQUARE], RADIUS_M, fence_m=FENCE
    )
    rng = np.random.default_rng(39)
    worst, changed = 0.0, 0
    for _ in range(60):
        pos = _f32(rng.uniform(-20, 20, 2))
        vel = _f32(rng.uniform(-0.7, 0.7, 2))
        goal = _f32(pos + rng.uniform(-15, 15, 2))
        nbr_p = _f32(pos + rng.uniform(-7, 7, (3, 2)))
        nbr_v = _f32(rng.uniform(-1, 1, (3, 2)))
        kinds = rng.integers(0, 3, 3).astype(np.uint8)
        sky = Sky.checked(pos_sigma_m=0.5, nbr_pos_sigma_m=np.full(3, 0.5), k=3)
        obs = Observation.shaped(pos, vel, 0.3, goal, nbr_p, nbr_v, np.zeros(3), sky)
        r = pol.onboard(1.0).step(obs, 0.0, nbr_kind=kinds, zones=zones)
        assert r.status == "ok" and r.decided
        held = pol.preferred(pos, vel, 0.3, goal, nbr_p, nbr_v, np.zeros(3))
        ref = safety.filter_one(
            pos, vel, held, nbr_p, nbr_v, cfg, pos_sigma_m=0.5, nbr_pos_sigma_m=np.full(3, 0.5),
            nbr_cooperative=kinds == 0, nbr_manned=kinds == 2, zones=zs,
        )  # fmt: skip
        worst = max(worst, float(np.abs(r.vel_m_s - ref).max()))
        changed += not np.allclose(ref, safety._clip_speed(np.asarray(held, float), 1.0))
    assert worst < 1e-5 and changed >= 20


def test_the_tick_keeps_the_manned_berth(lib):
    """A vehicle holding at its goal; an aircraft at 2 m/s passing 20 m aside. As plain
    traffic (kind 1) it needs nothing; as a manned aircraft (kind 2, the traffic table's kind
    for a manned emitter) the tick keeps CVY_MANNED_M (30 m)."""
    from firmware.cpolicy import CPolicy

    pol = CPolicy.load(sparse_rule=False)

    def fly(kind):
        onboard = pol.onboard(1.0)
        pos, vel = np.zeros(2), np.zeros(2)
        ipos, ivel = np.array([90.0, 20.0]), np.array([-2.0, 0.0])
        closest = np.inf
        for k in range(800):
            obs = Observation.shaped(pos, vel, 0.0, (0.0, 0.0), ipos[None], ivel[None], [math.pi])
            r = onboard.step(obs, k * DT_S, nbr_kind=[kind])
            assert r.status == "ok"
            vel = r.vel_m_s
            pos, ipos = pos + vel * DT_S, ipos + ivel * DT_S
            closest = min(closest, float(np.hypot(*(pos - ipos))))
        return closest

    assert fly(1) < 25.0  # plain traffic 20 m aside: no berth to keep
    assert fly(2) >= 30.0


def _fence_tokens(items) -> list[str]:
    toks = [str(len(items)), str(len(items))]
    for it in items:
        toks += [str(it.command), str(it.vertex_count)]
        toks += [repr(float(np.float32(x))) for x in (it.pos_n_m, it.pos_e_m, it.radius_m)]
    return toks


def test_fence_fuzz_under_asan_and_ubsan():
    """covey_fence_zones on valid fences (random concave and convex polygons, circles, a fence,
    return points) and on hostile mutations (NaN, inf, huge, counts that disagree with the
    items, an item count beyond the array), built with ASan + UBSan: the predicted status where
    one is predicted, never a crash, and no zones kept whenever it refuses."""
    from firmware import cfence as cf
    from firmware import hostbuild
    from tests.test_zones_filter import random_polygon

    driver = hostbuild.build_fence_driver(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    rng = np.random.default_rng(41)
    lines, want = [], []
    for i in range(250):
        items = [cf.FenceItem(cf.RETURN_POINT, 0, 1.0, 2.0)] if i % 4 == 0 else []
        for k in range(int(rng.integers(1, 4))):
            ring = random_polygon(rng) + np.array([25.0 * k, 0.0])
            items += cf.polygon_items(cf.POLYGON_EXCLUSION, ring)
        if i % 2:
            items.append(cf.FenceItem(cf.CIRCLE_EXCLUSION, 0, -30.0, 5.0, float(rng.uniform(1, 5))))
        if i % 3 == 0:
            items += cf.polygon_items(cf.POLYGON_INCLUSION, FENCE * 2.5)
        toks = _fence_tokens(items)
        lines.append(" ".join(toks))
        want.append("ok")
        vert = 2 + 5 * int(np.flatnonzero([it.command == cf.POLYGON_EXCLUSION for it in items])[0])
        for pos, value, status in [
            (vert + 2, "nan", "nonfinite"),  # a vertex
            (vert + 3, "-inf", "nonfinite"),
            (vert + 2, "3e6", "range"),  # beyond the position range
            (vert + 1, "2", "range"),  # a polygon's vertex count disagrees / is too small
            (vert + 1, "2147483647", "range"),
            (0, "-1", "range"),  # n_items
            (0, "4097", "range"),
            (0, str(len(items) - 1), "range" if items[-1].command != cf.CIRCLE_EXCLUSION else "ok"),
        ]:
            mutated = list(toks)
            mutated[pos] = value
            lines.append(" ".join(mutated))
            want.append(status)
        for _ in range(8):  # anything at all in any numeric slot but the framing
            mutated = list(toks)
            for _ in range(int(rng.integers(1, 4))):
                slot = int(rng.integers(2, len(toks)))
                if (slot - 2) % 5 < 2:  # command, vertex_count
                    mutated[slot] = str(rng.choice(["-1", "0", "3", "5001", "5002", "5003",
                                                    "5004", "65536", "-2147483648"]))  # fmt: skip
                else:
                    mutated[slot] = str(rng.choice(["nan", "inf", "-inf", "0", "-1", "1e30",
                                                    "-3e38", "1e-40"]))  # fmt: skip
            lines.append(" ".join(mutated))
            want.append("any")
    out, _ = hostbuild.run_driver(driver, "\n".join(lines) + "\n")
    assert len(out) == len(lines)
    seen: dict = {}
    for got, w in zip(out, want, strict=True):
        status, n_vertices, n_lines = got.split()
        seen[status] = seen.get(status, 0) + 1
        assert status in ("ok", "nonfinite", "range"), got
        assert w in ("any", status), (w, got)
        if status != "ok":
            assert n_vertices == "0" and n_lines == "0"
    assert seen.get("ok", 0) >= 250 and seen.get("range", 0) >= 1000
    print(f"\n[fence fuzz] {len(lines)} inputs under ASan+UBSan: {seen}, clean")
