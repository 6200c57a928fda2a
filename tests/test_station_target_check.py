"""The station's pre-checks of a target (groundstation/target_check.py): the flight core's goal
rule asked before anything is sent, at each vehicle's reported position sigma. A formation with a
slot its vehicle would refuse sends nothing and says which and why; a slot it would move is sent
moved, unless the moved slots end nearer each other than the spacing. Home and rally points keep
the zone clearance (plan editor, `covey plan load`, the station's upload)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from test_plan_files import ORIGIN, geojson, ll, write

from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.returning import ReturnConfig, Returns
from comms.plan import Fence, FleetPlan, RallyPoint, Zone
from groundstation import plan_edit as pe
from groundstation.formation import FormationError, FormationSpec, plan_formation
from groundstation.plan_cli import plan_cli
from groundstation.target_check import TargetCheck, landing_problems
from policy.goal_rule import ASSUMED_POS_SIGMA_M

# a keep-out zone east of the origin: its west edge at E 10, from N -20 to N 20
WALL = ((-20.0, 10.0), (20.0, 10.0), (20.0, 30.0), (-20.0, 30.0))
PLAN = FleetPlan("f", 1, 0, keep_out=(Zone(WALL, "pad"),))
ALT_M = 8.0


def _core(sigma_m: float) -> FlightCore:
    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0)
    core.set_plan(PLAN)
    obs = Observed(
        np.array([[0.0, -20.0, -ALT_M]]), np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool),
        np.full(1, 90.0), np.ones(1, bool), np.full(1, sigma_m),
    )  # fmt: skip
    core.observe(0.0, obs, gcs_alive=True)
    return core


@pytest.mark.parametrize("sigma_m", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("off_m", [0.5, 1.5, 2.0, 2.6, 3.0, 5.0])
def test_the_station_says_what_the_vehicles_core_would(sigma_m, off_m) -> None:
    """The reference is the flight core itself: same target, moved or refused alike."""
    target = np.array([3.0, 10.0 - off_m, -ALT_M])
    want_target, want_moved, want_refused = _core(sigma_m).check_target(0, target.copy())
    got = TargetCheck(PLAN, 3.0).check(target, sigma_m)
    assert got.refused == want_refused and got.moved == want_moved
    np.testing.assert_allclose(got.target_ned_m, want_target, atol=1e-9)


def test_a_plan_refusal_is_said_as_the_core_says_it() -> None:
    got = TargetCheck(PLAN, 3.0).check((0.0, 15.0, -ALT_M), 0.5)
    assert got.refused == "target inside keep-out zone 'pad'"
    assert TargetCheck(None, 3.0).check((0.0, 15.0, -ALT_M), 0.5).refused == ""


def _line(center_e_m: float, spacing_m: float = 4.0, heading_deg: float = 0.0) -> FormationSpec:
    return FormationSpec("line", spacing_m, (0.0, center_e_m), ALT_M, heading_deg)


# three vehicles south of where the slots are (each takes the slot north of it)
POS = {1: (-10.0, -4.0, -2.0), 2: (-10.0, 0.0, -2.0), 3: (-10.0, 4.0, -2.0)}


def test_a_slot_its_vehicle_would_refuse_refuses_the_formation_naming_it() -> None:
    # a line across the heading 0: slots at E -4, 0, 4 + centre; the last 2 m off the zone
    spec = _line(center_e_m=4.0)
    with pytest.raises(FormationError) as exc:
        plan_formation(spec, POS, 3.0, plan=PLAN, pos_sigma_m={1: 0.5, 2: 0.5, 3: 0.5})
    text = str(exc.value)
    assert text.startswith("vehicle 3 would refuse slot 2 (N 0.0 E 8.0 alt 8 m")
    assert "the goal is 2.0 m from keep-out zone 'pad', nearer than the 3.8 m" in text
    assert text.endswith("; nothing sent") and "\n" not in text
    # the same slots at the sigma 0 a vehicle reports for exact positions: 1.8 m, flown as is
    fp = plan_formation(spec, POS, 3.0, plan=PLAN, pos_sigma_m={1: 0.0, 2: 0.0, 3: 0.0})
    assert not any(fp.moved) and fp.targets_ned_m[2, 1] == pytest.approx(8.0)


def test_moved_slots_that_keep_the_spacing_are_sent_moved() -> None:
    # heading 90: the line stands north-south at E 6.9, every slot 3.1 m off the zone's edge,
    # 7 m apart (outside the 6.4 m berth of two vehicles at 0.5 m)
    spec = _line(center_e_m=6.9, spacing_m=7.0, heading_deg=90.0)
    pos = {1: (-7.0, 0.0, -2.0), 2: (0.0, 0.0, -2.0), 3: (7.0, 0.0, -2.0)}
    fp = plan_formation(spec, pos, 3.0, plan=PLAN, pos_sigma_m={1: 0.5, 2: 0.5, 3: 0.5})
    assert all(why.startswith("goal moved 0.") for why in fp.moved), fp.moved
    assert all("to 3.8 m from keep-out zone 'pad'" in why for why in fp.moved)
    np.testing.assert_allclose(fp.targets_ned_m[:, 1], 10.0 - 3.8, atol=0.1)
    np.testing.assert_allclose(fp.targets_ned_m[:, 0], [-7.0, 0.0, 7.0], atol=1e-6)
    assert "; goal moved 0." in fp.lines()[0]
    # nothing moves without a plan, or for vehicles reporting exact positions
    assert not any(plan_formation(spec, pos, 3.0, pos_sigma_m={1: 0.5}).moved)
    assert not any(plan_formation(spec, pos, 3.0, plan=PLAN).moved)


def test_moved_slots_nearer_each_other_than_the_spacing_refuse_the_formation() -> None:
    # the line's east end 3.1 m off the zone: moved 0.7-0.8 m west, 3.2-3.3 m from its neighbour
    spec = _line(center_e_m=2.9)
    with pytest.raises(FormationError) as exc:
        plan_formation(spec, POS, 3.0, plan=PLAN, pos_sigma_m={1: 0.5, 2: 0.5, 3: 0.5})
    text = str(exc.value)
    assert text.startswith("vehicle 3's slot 2 would be moved (goal moved 0.")
    assert re.search(
        r" to 3\.[23]\d m from vehicle 2's slot 1, closer than the formation's 4\.00 m", text
    )
    assert text.endswith("; nothing sent")
    # the same line with the vehicles reporting exact positions: nothing moves, sent as is (at
    # 0.5 m the 4 m spacing is inside their 6.4 m berth: `test_slots_inside_the_berth...`)
    fp = plan_formation(spec, POS, 3.0, plan=PLAN, pos_sigma_m={1: 0.0, 2: 0.0, 3: 0.0})
    assert not any(fp.moved) and fp.targets_ned_m[2, 1] == pytest.approx(6.9)


def test_slots_inside_the_berth_at_the_reported_sigmas_refuse_the_formation() -> None:
    """Vehicles on plain GNSS keep 3.6 m + 4 sqrt(sigma_i^2 + sigma_j^2) between estimates: a
    formation tighter than that for the sigmas they report is refused, naming the pair and the
    spacing that would hold; exact positions (sigma 0) fly the same slots."""
    spec = _line(center_e_m=-20.0, spacing_m=5.0)  # no zone near: only the berth matters
    with pytest.raises(FormationError) as exc:
        plan_formation(spec, POS, 3.0, pos_sigma_m={1: 0.5, 2: 0.5, 3: 0.5})
    text = str(exc.value)
    assert text.startswith("vehicles 1 and 2 would hover 5.0 m apart, inside the 6.4 m")
    assert "(0.5 m, 0.5 m)" in text and "widen --spacing-m to 6.5 m" in text
    assert text.endswith("; nothing sent")
    # one vehicle at 1 m among exact ones: its pairs need 3.6 + 4 x 1 = 7.6 m
    with pytest.raises(FormationError, match=r"vehicles 2 and 3 .* inside the 7\.6 m .* to 7\.6 m"):
        plan_formation(spec, POS, 3.0, pos_sigma_m={1: 0.0, 2: 0.0, 3: 1.0})
    assert plan_formation(spec, POS, 3.0, pos_sigma_m={1: 0.0, 2: 0.0, 3: 0.0}).targets_ned_m.size
    assert plan_formation(_line(-20.0, 6.5), POS, 3.0, pos_sigma_m={1: 0.5, 2: 0.5, 3: 0.5})


# -- home and rally points ----------------------------------------------------------------------
def _draft(**over) -> pe.Draft:
    fence = Fence(((-100.0, -100.0), (-100.0, 100.0), (100.0, 100.0), (100.0, -100.0)))
    return pe.draft_of(FleetPlan("f", 3, 0, fence, (Zone(WALL, "pad"),), **over))


@pytest.mark.parametrize(
    ("step", "reason"),
    [
        (lambda d: pe.set_home(d, 0, 8), r"^home \(0.0, 8.0\) m is 2.0 m from keep-out zone 'pad', "
         r"nearer than the 3.8 m the vehicles' filter keeps from it at a 0.5 m position sigma"),
        (lambda d: pe.add_rally(d, 0, 98, name="edge"),
         r"^rally point 'edge' \(0.0, 98.0\) m is 2.0 m from the fence, nearer than the 3.8 m"),
        (lambda d: pe.add_rally(d, 22, 20), r"^a rally point \(22.0, 20.0\) m is 2.0 m from "),
        (lambda d: pe.move_rally(pe.add_rally(d, 0, -20), 1, 0, 7.5), r"is 2.5 m from keep-out"),
        (lambda d: pe.close_zone(
            pe.add_corner(pe.add_corner(pe.add_corner(pe.set_home(d, -50, -50), -48, -48), -40,
                                        -48), -40, -40), "shed"),
         r"^home \(-50.0, -50.0\) m is 2.8 m from keep-out zone 'shed'"),
    ],
)  # fmt: skip
def test_home_and_rally_points_keep_the_zone_clearance(step, reason) -> None:
    d = _draft()
    with pytest.raises(pe.EditRefused, match=reason):
        step(d)
    # its eastern pads (E +10 m) 3.9 m off the zone
    assert pe.set_home(d, 0, -3.9).geometry.rally == (RallyPoint(0, -3.9, 0.0, "home"),)


def test_a_home_already_too_near_blocks_no_edit_elsewhere_and_separation_counts() -> None:
    near = _draft(rally=(RallyPoint(0, 8, 0, "home"),))  # pushed before the rule
    d = pe.add_rally(near, -50, -50)
    assert len(d.geometry.rally) == 2
    with pytest.raises(pe.EditRefused, match=r"^home \(0.0, 7.0\) m is 3.0 m"):
        pe.set_home(near, 0, 7)
    # at 2 m separation the filter keeps 1.2 m + 2 m: 3.2 m, so 3.5 m off is fine there
    small = pe.draft_of(FleetPlan("f", 3, 0, keep_out=(Zone(WALL, "pad"),)), 2.0)
    home = pe.set_home(small, 0, -3.5).geometry  # its eastern pads 3.5 m off
    assert home.rally[0].e_m == -3.5 and landing_problems(home, 2.0, ASSUMED_POS_SIGMA_M) == []
    problems = landing_problems(home, 3.0, ASSUMED_POS_SIGMA_M)
    assert {p.point for p in problems} == set(home.rally)
    assert [p.pad_no for p in problems] == [5, 10, 15, 20, 25]  # the eastern column
    assert landing_problems(home, 3.0, pos_sigma_m=0.3) == []  # 1.8 + 1.2 m


def test_the_pads_checked_are_where_returning_vehicles_land() -> None:
    """The station's pads are agent/returning.py's: a vehicle returning to the point lands on
    the pad its refusal names for its id (pad (id - 1) mod 25 + 1; 30 lands on pad 5)."""
    small = pe.draft_of(FleetPlan("f", 3, 0, keep_out=(Zone(WALL, "pad"),)), 2.0)
    home = pe.set_home(small, 0, -3.5).geometry
    problems = landing_problems(home, 3.0)
    assert [p.pad_no for p in problems] == [5, 10, 15, 20, 25]
    assert problems[0].why.startswith(
        "home: landing pad 5 (N -10.0, E 6.5 m) is 3.5 m from keep-out zone 'pad', nearer than "
        "the 3.8 m clearance"
    )
    ids = [p.pad_no for p in problems] + [30]
    returns = Returns(ReturnConfig(), np.array(ids))
    for i, p in enumerate([*problems, problems[0]]):
        took_off_at = np.array([500.0, 500.0, 0.0])  # farther than the point: it lands there
        returns.enter(i, np.array([0.0, -3.5, -10.0]), took_off_at, [(0.0, -3.5)], 1.0, 0.5)
        found = re.search(r"\(N (\S+), E (\S+) m\)", p.why)
        assert found is not None
        assert returns.spot_ne_m[i] == pytest.approx([float(c) for c in found.groups()])


def test_covey_plan_load_refuses_home_near_a_zone(tmp_path, capsys) -> None:
    home = {"type": "Feature", "properties": {"role": "home"},
            "geometry": {"type": "Point", "coordinates": list(reversed(ll(48, 60)))}}  # fmt: skip
    path = write(tmp_path, geojson(feature3=home))
    origin = f"--origin={ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}"
    with pytest.raises(SystemExit) as exit_:
        plan_cli(["load", str(path), "--dir", str(tmp_path / "nowhere"), origin])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert "home (48.0, 60.0) m is 2.0 m from keep-out zone 'school'" in err[0], err
    # 3.5 m off: too near at the default 3 m separation (3.8 m), not at --separation-m 2 (3.2 m)
    home["geometry"]["coordinates"] = list(reversed(ll(46.5, 60)))
    path = write(tmp_path, geojson(feature3=home))
    for extra, near in (([], True), (["--separation-m", "2"], False)):
        with pytest.raises(SystemExit):
            plan_cli(["load", str(path), "--dir", str(tmp_path / "nowhere"), origin, *extra])
        err = capsys.readouterr().err
        assert ("home (46.5, 60.0) m is 3.5 m" in err) == near, err  # else: no authority there
