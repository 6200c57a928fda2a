"""Plan files and `covey plan`: GeoJSON and QGC .plan files in, checked geometry out; every bad
file one line and exit 2; load signs (authority or station), show verifies, push reaches a real
member over Zenoh and counts it."""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys

import pytest

from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan_io import CIRCLE_VERTICES, BadPlanError, read_plan_file, read_signed_plan
from comms.plan_sync import PlanSync
from comms.schema import Role
from comms.session import MeshConfig, free_tcp_port
from groundstation.plan_cli import plan_cli
from tests.conftest import REPO, wait_until
from trust.auth import load_auth
from trust.authority import throwaway_fleet

ORIGIN = GeoOrigin(48.7490, 9.1050, 450.0)
FLEET = "planfiles"


def ll(n_m: float, e_m: float) -> tuple[float, float]:
    """(lat, lon) of a local point."""
    lat, lon, _ = ORIGIN.to_global(n_m, e_m, 0.0)
    return lat, lon


def ring_lonlat(vertices_ne):
    out = [[ll(n, e)[1], ll(n, e)[0]] for n, e in vertices_ne]
    return out + [out[0]]


FENCE_NE = [(-100, -100), (-100, 300), (300, 300), (300, -100)]
SCHOOL_NE = [(50, 50), (50, 80), (80, 80), (80, 50)]


def geojson(**over) -> dict:
    features = [
        {
            "type": "Feature",
            "properties": {"role": "fence", "floor_m": 2, "ceiling_m": 120},
            "geometry": {"type": "Polygon", "coordinates": [ring_lonlat(FENCE_NE)]},
        },
        {
            "type": "Feature",
            "properties": {"role": "keep_out", "name": "school"},
            "geometry": {"type": "Polygon", "coordinates": [ring_lonlat(SCHOOL_NE)]},
        },
        {
            "type": "Feature",
            "properties": {"role": "keep-out", "name": "pylons", "ceiling_m": 40},
            "geometry": {
                "type": "MultiPolygon",
                "coordinates": [
                    [ring_lonlat([(200, 0), (200, 10), (210, 10)])],
                    [ring_lonlat([(220, 0), (220, 10), (230, 10)])],
                ],
            },
        },
        {
            "type": "Feature",
            "properties": {"role": "home"},
            "geometry": {"type": "Point", "coordinates": list(reversed(ll(0, 0)))},
        },
        {
            "type": "Feature",
            "properties": {"role": "rally", "name": "north field", "alt_m": 5},
            "geometry": {"type": "Point", "coordinates": list(reversed(ll(250, 0)))},
        },
    ]
    doc = {"type": "FeatureCollection", "features": features}
    for k, v in over.items():
        if k.startswith("feature"):
            features[int(k[7:])] = v
        else:
            doc[k] = v
    return doc


def qgc() -> dict:
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "mission": {"plannedHomePosition": [*ll(0, 0), 450.0], "items": [], "version": 2},
        "geoFence": {
            "version": 2,
            "polygons": [
                {"inclusion": True, "polygon": [list(ll(n, e)) for n, e in FENCE_NE], "version": 1},
                {"inclusion": False, "polygon": [list(ll(n, e)) for n, e in SCHOOL_NE], "version": 1},
            ],
            "circles": [
                {"circle": {"center": list(ll(150, 150)), "radius": 20.0}, "inclusion": False,
                 "version": 1},
            ],
        },
        "rallyPoints": {"points": [[*ll(250, 0), 15.0]], "version": 2},
    }  # fmt: skip


def write(tmp_path, doc, name="plan.geojson"):
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


@contextlib.contextmanager
def _plan_follower(authority):
    """A router on a free loopback port and vehicle 1 of `authority` following the fleet plan
    behind it: (the router's endpoint, the vehicle's PlanSync)."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    vehicle = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    with (
        Mesh(MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(ep,))),
        Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(ep,)), auth=vehicle) as v,
        PlanSync(v.session, FLEET, vehicle) as follower,
    ):
        yield ep, follower


def test_geojson_becomes_local_metres() -> None:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        g = read_plan_file(write(Path(d), geojson()), ORIGIN)
    assert g.fence.floor_alt_m == 2 and g.fence.ceiling_alt_m == 120
    for (n, e), (n0, e0) in zip(g.fence.vertices_ne_m, FENCE_NE, strict=True):
        assert abs(n - n0) < 0.01 and abs(e - e0) < 0.01  # the closing vertex dropped
    assert [z.name for z in g.keep_out] == ["school", "pylons 1", "pylons 2"]
    assert g.keep_out[1].ceiling_alt_m == 40
    assert [r.name for r in g.rally] == ["home", "north field"] and g.rally[1].alt_m == 5


def test_qgc_plan_fence_zones_circle_and_rally(tmp_path) -> None:
    g = read_plan_file(write(tmp_path, qgc(), "m.plan"), ORIGIN, ceiling_alt_m=80.0)
    assert len(g.fence.vertices_ne_m) == 4 and g.fence.ceiling_alt_m == 80.0
    school, circle = g.keep_out
    assert len(school.vertices_ne_m) == 4 and len(circle.vertices_ne_m) == CIRCLE_VERTICES
    # An exclusion circle becomes its circumscribed polygon: every edge at least 20 m out.
    r_min = min(math.hypot(n - 150, e - 150) for n, e in circle.vertices_ne_m)
    assert 20.0 < r_min < 20.0 / math.cos(math.pi / CIRCLE_VERTICES) + 0.01
    assert [r.name for r in g.rally] == ["home", "rally 1"] and g.rally[1].alt_m == 15.0
    assert any("32-gon" in note for note in g.notes)


BOWTIE = [(0, 0), (0, 50), (50, 0), (50, 50)]
BAD = {
    "not json": ("{oops", "not JSON"),
    "too deep": ("[" * 40 + "]" * 40, "nests deeper"),
    "not a plan": ({"type": "Feature"}, "neither a GeoJSON"),
    "self-intersecting": (
        geojson(feature1={"type": "Feature", "properties": {"role": "keep_out", "name": "bow"},
                          "geometry": {"type": "Polygon", "coordinates": [ring_lonlat(BOWTIE)]}}),
        "not a valid polygon: Self-intersection",
    ),
    "zone covers home": (
        geojson(feature1={"type": "Feature", "properties": {"role": "keep_out", "name": "pad"},
                          "geometry": {"type": "Polygon", "coordinates": [
                              ring_lonlat([(-5, -5), (-5, 5), (5, 5), (5, -5)])]}}),
        "keep-out zone 'pad' covers home",
    ),
    "home outside the fence": (
        geojson(feature3={"type": "Feature", "properties": {"role": "home"},
                          "geometry": {"type": "Point", "coordinates": list(reversed(ll(900, 0)))}}),
        "home (900.0, 0.0) m is outside the fence",
    ),
    "two fences": (
        geojson(feature1={"type": "Feature", "properties": {"role": "fence"},
                          "geometry": {"type": "Polygon", "coordinates": [ring_lonlat(SCHOOL_NE)]}}),
        "a second fence polygon",
    ),
    "holes": (
        geojson(feature1={"type": "Feature", "properties": {"role": "keep_out"},
                          "geometry": {"type": "Polygon", "coordinates": [
                              ring_lonlat(FENCE_NE), ring_lonlat(SCHOOL_NE)]}}),
        "holes are not supported",
    ),
    "unknown role": (
        geojson(feature1={"type": "Feature", "properties": {"role": "nofly"},
                          "geometry": {"type": "Polygon", "coordinates": [ring_lonlat(SCHOOL_NE)]}}),
        "properties.role must be one of",
    ),
    "lat lon swapped": (
        geojson(feature4={"type": "Feature", "properties": {"role": "rally"},
                          "geometry": {"type": "Point", "coordinates": [48.7, 99.1]}}),
        "latitude 99.1 is outside",
    ),
    "NaN ceiling": (
        json.dumps(geojson()).replace('"ceiling_m": 120', '"ceiling_m": NaN'),
        "ceiling_m must be a finite number",
    ),
    "floor above ceiling": (
        json.dumps(geojson()).replace('"floor_m": 2', '"floor_m": 200'),
        "floor 200 m must be below its ceiling 120 m",
    ),
    "circle radius": (
        json.dumps(qgc()).replace('"radius": 20.0', '"radius": -3'),
        "radius -3 m is outside",
    ),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(BAD))
def test_every_bad_file_is_one_line_and_exit_2(tmp_path, capsys, name) -> None:
    doc, why = BAD[name]
    path = write(tmp_path, doc)
    with pytest.raises(BadPlanError, match=why.replace("(", r"\(").replace(")", r"\)")):
        read_plan_file(path, ORIGIN)
    with pytest.raises(SystemExit) as exit_:
        plan_cli(["load", str(path), "--dir", str(tmp_path / "nowhere")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1 and why.split(":")[0] in err[0], err


def test_missing_oversized_and_fifo_files_are_one_line(tmp_path, capsys) -> None:
    import os

    big = tmp_path / "big.geojson"
    big.write_bytes(b" " * 4_000_001)
    fifo = tmp_path / "fifo.geojson"
    os.mkfifo(fifo)
    for path, why in ((tmp_path / "none.geojson", "does not exist"), (big, "over the"),
                      (fifo, "not a regular file")):  # fmt: skip
        with pytest.raises(SystemExit) as exit_:
            plan_cli(["show", str(path), "--dir", str(tmp_path)])
        assert exit_.value.code == 2 and why in capsys.readouterr().err


def test_load_signs_show_verifies_push_reaches_a_member(tmp_path, capsys) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    keys_dir = str(authority.dir)
    src = write(tmp_path, qgc(), "field.plan")
    origin = f"--origin={ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}"
    assert plan_cli(["load", str(src), "--dir", keys_dir, origin, "--ceiling-m", "90"]) == 0
    out = capsys.readouterr().out
    assert "signed by the fleet authority" in out and "keep-out 'circle 0'" in out
    first = read_signed_plan(authority.dir / "plan.bin")
    assert first.signer_id == 0 and first.fence.ceiling_alt_m == 90
    assert plan_cli(["show", "--dir", keys_dir]) == 0
    assert "signature verified" in capsys.readouterr().out
    # A station signs the next version; it is newer than the authority's.
    station_key = str(authority.member_path(Role.STATION, 1))
    argv = ["load", str(src), "--dir", keys_dir, origin, "--key-file", station_key]
    assert plan_cli(argv) == 0
    second = read_signed_plan(authority.dir / "plan.bin")
    assert second.signer_id == 1 and second.version > first.version
    assert plan_cli(["show", "--dir", keys_dir]) == 0
    assert "signed by station 1, signature verified" in capsys.readouterr().out
    # Push (a real `covey plan push` process) to a keyed vehicle's follower behind a router.
    with _plan_follower(authority) as (ep, follower):
        push = subprocess.run(
            [sys.executable, "-m", "covey_cli", "plan", "push", "--dir", keys_dir, "--connect", ep],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert push.returncode == 0, push.stderr
        assert f"pushed fleet {FLEET} plan v{second.version}: 1 member(s) confirmed" in push.stdout
        assert wait_until(lambda: follower.plan is not None, 5)
        assert follower.plan.version == second.version


def test_load_and_push_refuse_a_landing_pad_too_near_a_zone(tmp_path, capsys) -> None:
    """'north field' 12 m off the school, but its south-west pad (of 5 x 5, 5 m apart) 2 m off:
    load refuses it naming the point, the pad and the zone; a plan signed without that check
    (before it existed) is refused by push with the same reason, exit 2, and nothing reaches a
    member listening on the mesh."""
    from comms.plan_io import write_signed_plan
    from trust.auth import sign_plan

    rally = {"type": "Feature", "properties": {"role": "rally", "name": "north field"},
             "geometry": {"type": "Point", "coordinates": list(reversed(ll(92, 65)))}}  # fmt: skip
    path = write(tmp_path, geojson(feature4=rally))
    why = (
        "rally point 'north field': landing pad 1 (N 82.0, E 55.0 m) is 2.0 m from keep-out "
        "zone 'school', nearer than the 3.8 m clearance"
    )
    origin = f"--origin={ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}"
    with pytest.raises(SystemExit) as exit_:
        plan_cli(["load", str(path), "--dir", str(tmp_path / "nowhere"), origin])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1 and why in err[0], err
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1])
    unchecked = sign_plan(authority.key, read_plan_file(path, ORIGIN).plan(FLEET, 5, 0))
    write_signed_plan(authority.dir / "plan.bin", unchecked)
    with _plan_follower(authority) as (ep, follower):
        with pytest.raises(SystemExit) as exit_:
            plan_cli(["push", "--dir", str(authority.dir), "--connect", ep, "--duration-s", "1"])
        err = capsys.readouterr().err.strip().splitlines()
        assert exit_.value.code == 2 and len(err) == 1, err
        assert "plan.bin (plan v5, nothing sent): " + why in err[0], err
        assert not wait_until(lambda: follower.plan is not None, 1.0)
        # at a 2 m separation the filter keeps 3.2 m: the pad 2 m off is still refused
        with pytest.raises(SystemExit):
            plan_cli(["push", "--dir", str(authority.dir), "--separation-m", "2", "--connect", ep])
        err = capsys.readouterr().err
        assert "is 2.0 m from keep-out zone 'school', nearer than the 3.2 m" in err
        with pytest.raises(SystemExit):
            plan_cli(["push", "--dir", str(authority.dir), "--rally-pads", "0", "--connect", ep])
        assert "pads must be within 1..10000, got 0" in capsys.readouterr().err
        # a fleet whose returns lay 4 pads 2 m apart (the agents' --rally-pads 4
        # --rally-pad-spacing-m 2) lands 11 m off the school: sent, and held
        pads = ["--rally-pads", "4", "--rally-pad-spacing-m", "2"]
        assert plan_cli(["push", "--dir", str(authority.dir), *pads, "--connect", ep]) == 0
        assert wait_until(lambda: follower.plan is not None and follower.plan.version == 5, 5)
