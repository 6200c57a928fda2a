"""Ground-station input validation, the kill guard, scenarios, frames, HTML, and `covey cmd` args."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from comms.commands import CommandResult, Outcome, OutcomeStatus
from comms.schema import Command, CommandKind, Mode, VehicleState
from groundstation import inputs, ops, scenarios
from groundstation.dispatch import Dispatched, KillGuard, build_command
from groundstation.fleet import FleetModel
from groundstation.frames import ground_hit_ned, heading_to_wxyz, ned_to_scene, scene_to_ned
from groundstation.inputs import InputError
from groundstation.tables import ack_matrix, fleet_table

BAD_NUMBERS = [math.nan, math.inf, -math.inf, "nan", "inf", "abc", "", None, True]


@pytest.mark.parametrize("raw", BAD_NUMBERS)
def test_non_finite_or_non_numbers_are_refused_with_a_message(raw):
    with pytest.raises(InputError, match="Take-off altitude above origin"):
        inputs.takeoff(raw)
    with pytest.raises(InputError, match="North"):
        inputs.goto_local(raw, 0.0, 5.0)
    with pytest.raises(InputError, match="Altitude above origin"):
        inputs.goto_local(0.0, 0.0, raw)
    with pytest.raises(InputError, match="Latitude"):
        inputs.goto_global(raw, 9.0, 450.0)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: inputs.takeoff(0.1), r"outside the allowed range \[0.5, 500\] m"),
        (lambda: inputs.takeoff(900), "outside"),
        (lambda: inputs.goto_local(0, 0, -200), r"Altitude above origin: -200 m is outside"),
        (lambda: inputs.goto_local(40, 40, 5, limit_m=50), "beyond 50 m"),
        (lambda: inputs.goto_local(60, 0, 5, limit_m=50), "North"),
        (lambda: inputs.goto_global(91, 0, 10), "Latitude"),
        (lambda: inputs.goto_global(0, 181, 10), "Longitude"),
        (lambda: inputs.goto_global(0, 0, 20_000), "Altitude AMSL"),
        (lambda: inputs.simple(CommandKind.TAKEOFF), "needs parameters"),
    ],
)
def test_out_of_range_is_refused_with_a_message(build, match):
    with pytest.raises(InputError, match=match):
        build()


def test_valid_inputs_build_commands_the_wire_accepts():
    for req in (
        inputs.takeoff("7.5"),
        inputs.goto_local(10, -4, 6),
        inputs.goto_global(48.75, 9.1, 455),
        inputs.simple(CommandKind.KILL),
    ):
        cmd = build_command(req, (1, 2), source_id=1, stamp_ns=5)
        assert Command.decode(cmd.encode()) == cmd
    assert inputs.takeoff(7.5).params == (7.5, 0.0, 0.0)
    assert inputs.goto_local(10, -4, 6).describe() == "goto N 10.0 E -4.0 alt 6.0 m above origin"


def test_one_altitude_convention_up_with_its_datum_in_the_form_and_the_cli():
    """Altitude up, in metres, above the origin for take-off and local gotos, AMSL for global;
    NED (down) only on the wire. `covey cmd goto 10 10 5` flies 5 m up, as the form does."""
    req = inputs.goto_local(10, 10, 5)
    assert req.params == (10.0, 10.0, -5.0)  # the wire's NED down
    parser = ops.cmd_parser()
    args = parser.parse_args(["goto", "10", "10", "5", "--to", "1"])
    assert ops._request(args) == req
    args = parser.parse_args(["goto-global", "48.75", "9.1", "455", "--to", "1"])
    assert ops._request(args).describe() == "goto lat 48.750000 lon 9.100000 alt 455.0 m AMSL"
    assert inputs.takeoff(5).describe() == "takeoff to 5.0 m above origin"
    goto_help = parser._subparsers._group_actions[0].choices["goto"].format_help()
    assert "above the fleet origin" in goto_help and "down" not in goto_help.lower()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("all", ()),
        (" ALL ", ()),
        ("3", (3,)),
        ("1,2,5", (1, 2, 5)),
        ("4-6, 1", (1, 4, 5, 6)),
        ("2,2", (2,)),
    ],
)
def test_targets_parse(text, expected):
    assert inputs.targets(text) == expected


@pytest.mark.parametrize("text", ["", "  ", "x", "0", "3-1", "1,,b", "70000", "1-5000"])
def test_bad_targets_are_refused(text):
    with pytest.raises(InputError, match="Targets"):
        inputs.targets(text)


def test_unknown_target_is_refused_when_the_fleet_is_known():
    assert inputs.targets("1,2", known={1, 2, 3}) == (1, 2)
    with pytest.raises(InputError, match="no vehicle 9"):
        inputs.targets("1,9", known={1, 2, 3})


def test_kill_guard_needs_arm_then_confirm_within_the_window():
    guard = KillGuard(window_s=5.0)
    assert not guard.confirm(0.0)  # confirm alone never kills
    guard.arm(10.0)
    assert guard.armed(12.0) and guard.remaining_s(12.0) == pytest.approx(3.0)
    assert guard.confirm(14.9)
    assert not guard.confirm(15.0)  # one confirm per arm
    guard.arm(20.0)
    assert not guard.confirm(25.1)  # too late
    guard.arm(30.0)
    guard.disarm()
    assert not guard.confirm(30.1)


def test_swap_sends_each_vehicle_to_the_antipode_of_its_slot():
    positions = {
        1: (5.0, 0.0, -5.0),
        2: (0.0, 5.0, -5.0),
        3: (-5.0, 0.0, -5.0),
        4: (0.0, -5.0, -5.0),
    }
    goals = scenarios.swap_goals(positions, radius_m=10.0)
    for vid, (n, e, d) in goals.items():
        assert math.hypot(n, e) == pytest.approx(10.0)
        assert d == -5.0
        pn, pe, _ = positions[vid]
        # The goal is on the far side of the centre from where the vehicle is.
        assert n * pn + e * pe < 0
    assert len({(round(n, 3), round(e, 3)) for n, e, _ in goals.values()}) == 4
    # Swapping twice brings everyone back to their first slot.
    again = scenarios.swap_goals(goals, radius_m=10.0)
    first = scenarios.swap_goals({v: (-g[0], -g[1], g[2]) for v, g in goals.items()}, radius_m=10.0)
    assert again.keys() == first.keys()


def test_landed_vehicles_get_the_default_altitude():
    goals = scenarios.swap_goals({1: (1.0, 0.0, 0.0), 2: (-1.0, 0.0, -8.0)}, radius_m=5.0)
    assert goals[1][2] == -scenarios.DEFAULT_ALT_M and goals[2][2] == -8.0


def test_random_goals_are_in_the_disc_and_spaced():
    positions = {i: (0.0, 0.0, -5.0) for i in range(1, 11)}
    goals = scenarios.random_goals(positions, 20.0, np.random.default_rng(1), min_spacing_m=4.0)
    pts = [(n, e) for n, e, _ in goals.values()]
    assert all(math.hypot(*p) <= 20.0 for p in pts)
    assert min(math.dist(a, b) for i, a in enumerate(pts) for b in pts[i + 1 :]) >= 4.0
    assert goals == scenarios.random_goals(
        positions, 20.0, np.random.default_rng(1), min_spacing_m=4.0
    )


def test_ned_scene_round_trip_and_axes():
    ned = np.array([[1.0, 2.0, -3.0], [-4.0, 5.0, 6.0]])
    assert ned_to_scene(ned).tolist() == [
        [2.0, 1.0, 3.0],
        [5.0, -4.0, -6.0],
    ]  # x east, y north, z up
    assert np.allclose(scene_to_ned(ned_to_scene(ned)), ned)
    w, x, y, z = heading_to_wxyz(math.pi / 2)  # east: nose (+y) turns to +x, a -90 deg yaw
    assert (w, x, y) == pytest.approx((math.cos(math.pi / 4), 0, 0)) and z == pytest.approx(
        -math.sin(math.pi / 4)
    )


def test_ground_click_hits_the_ground_or_nothing():
    assert ground_hit_ned((3.0, 4.0, 10.0), (0.0, 0.0, -1.0)) == pytest.approx((4.0, 3.0))
    assert ground_hit_ned((0.0, 0.0, 10.0), (1.0, 0.0, -1.0)) == pytest.approx((0.0, 10.0))
    assert ground_hit_ned((0.0, 0.0, 10.0), (0.0, 1.0, 0.2)) is None  # above the horizon
    assert ground_hit_ned((0.0, 0.0, math.nan), (0.0, 0.0, -1.0)) is None


def test_fleet_table_and_ack_matrix_show_what_matters():
    model = FleetModel()
    model.on_presence(1, True, 0)
    model.on_presence(2, True, 0)
    model.on_state(
        VehicleState(1, 1, 1, (0.0, 0.0, -5.0), (0.0, 0.0, 0.0), 0.0, Mode.GOTO, True), 0
    )
    model.on_state(
        VehicleState(2, 1, 1, (1.0, 0.0, -5.0), (0.0, 0.0, 0.0), 0.0, Mode.HOLDING, True), 0
    )
    model.on_presence(2, False, 0)
    page = fleet_table(model.snapshot(0))
    assert (
        "GOTO" in page
        and "LOST" in page
        and "TOO CLOSE" in page
        and "<b>1</b> of 2 vehicles present" in page
    )
    cmd = build_command(inputs.takeoff(5), (), 1, 0)
    res = CommandResult(
        cmd,
        {
            1: Outcome(1, OutcomeStatus.ACCEPTED, "", None, 0.01),
            2: Outcome(2, OutcomeStatus.REJECTED, "already flying <x>", None, 0.01),
            3: Outcome(3, OutcomeStatus.TIMEOUT, "no answer within 2 s", None, 2.0),
        },
    )
    page = ack_matrix(Dispatched("takeoff to 5 m → all", (res,)))
    assert 'data-vehicle="2" data-status="rejected"' in page and "already flying &lt;x&gt;" in page
    assert 'data-status="timeout"' in page and "1 accepted · 1 rejected · 1 timeout" in page


@pytest.mark.parametrize(
    "argv",
    [
        ["takeoff", "nan", "--to", "all"],
        ["takeoff", "5"],  # no --to
        ["takeoff", "5", "--to", "x"],
        ["goto", "1", "2", "--to", "1"],  # missing the altitude
        ["goto", "1", "2", "inf", "--to", "1"],
        ["goto-global", "95", "0", "10", "--to", "1"],
        ["fly", "--to", "1"],
        ["land", "--to", "1", "--timeout-s", "0"],
    ],
)
def test_covey_cmd_bad_arguments_are_argparse_errors(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        ops.cmd_cli(argv)
    assert exc.value.code == 2
    assert "error" in capsys.readouterr().err


def test_covey_cmd_kill_without_confirmation_sends_nothing(capsys):
    rc = ops.cmd_cli(
        ["kill", "--to", "all", "--connect", "tcp/127.0.0.1:9"], stdin=io.StringIO("no\n")
    )
    assert rc == 1
    assert "nothing sent" in capsys.readouterr().err
