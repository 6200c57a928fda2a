"""Editing the fleet plan in real Chromium, on a keyed in-process station and a real keyed
`covey agent` process: a keep-out zone clicked corner by corner on the ground, closed and pushed
from the 'Edit fleet plan' folder reaches the agent, which refuses a goto inside it; the station
draws the agent's route around it and lists the push in its command log; a self-crossing zone is
refused in the panel with its reason and nothing is pushed; a fence clicked around the fleet, a
corner of it moved by number (zone 0) and pushed bounds the agent's gotos; a rally point clicked
on the ground (one clicked inside the zone refused), moved by number and pushed is where the
agent returns to."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
import shapely
from conftest import REPO, keyed_agent_argv, wait_until
from test_gcs_browser import CHROMIUM, CHROMIUM_ARGS
from test_gcs_layout import screen_xy

from agent.returning import ReturnConfig
from comms.commands import OutcomeStatus, new_nonce
from comms.schema import Command, CommandKind, Role
from comms.session import MeshConfig, free_tcp_port
from groundstation.plan_draft_view import DRAFT_PATH
from groundstation.plan_editor import (
    CLICK_ADD,
    CLICK_MOVE,
    CLICK_RALLY,
    CORNER_E,
    CORNER_N,
    CORNER_NO,
    GROUND_CLICK,
    MOVE_RALLY,
    RALLY_NO,
    ZONE_NAME,
    ZONE_NO,
)
from groundstation.station import GcsConfig, GroundStation
from kit.procs import ChildGroup, python_env
from tests.test_plan_files import ORIGIN
from trust.authority import throwaway_fleet

pytestmark = [pytest.mark.browser, pytest.mark.e2e]
sync_api = pytest.importorskip("playwright.sync_api")

FLEET = "planedit"
ZONE_NE_M = ((0.0, 0.0), (0.0, 12.0), (12.0, 12.0), (12.0, 0.0))
"""The zone clicked (north, east); the agent starts at N 20, E 20, beyond its corner."""
BOW_TIE_NE_M = ((20.0, -8.0), (28.0, 0.0), (20.0, 0.0), (28.0, -8.0))
"""Clear of the kill window (bottom left) and of the agent's route."""
FENCE_NE_M = ((-15.0, -15.0), (-15.0, 30.0), (30.0, 30.0), (30.0, -15.0))
"""The fence clicked around the zone and the agent, which has flown to N -8, E -8."""
MOVED_NE_M = (-15.0, 10.0)
"""Where the fence's corner 2 moves: N -10, E 20 was inside the clicked fence, is outside it."""
RALLY_NE_M = (20.0, 0.0)
"""The rally point (inside the fence, clear of the zone): nearer the agent at N -8, E -8 than
where it took off (N 20, E 20), so it returns to its pad there."""
RETURNS = ReturnConfig(rally_pads=4, rally_pad_spacing_m=2.0)
"""The agent's pads around a rally point, and the station's check of them: the default 5 x 5
grid 5 m apart would not fit between this small fence and the zone (the station refuses it)."""
PADS_ARGV = ["--rally-pads=4", "--rally-pad-spacing-m=2"]


def choose(page, label: str, option: str, tries: int = 5) -> None:
    """Pick `option` in the dropdown `label`: open it and click the option, opened again when
    its list did not come up in 10 s (on a loaded machine a click can land while the folder
    is still opening, and that list never shows)."""
    for k in range(tries):
        page.get_by_label(label, exact=True).click(force=True)
        try:
            page.get_by_role("option", name=option).click(force=True, timeout=10_000)
            return
        except sync_api.Error:
            if k == tries - 1:
                raise
            page.keyboard.press("Escape")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    return throwaway_fleet(tmp_path_factory.mktemp("keys"), FLEET, vehicles=[1], stations=[1])


@pytest.fixture(scope="module")
def gcs(fleet):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg = GcsConfig(
        mesh=MeshConfig(fleet=FLEET, mode="peer", connect=(), listen=(ep,)),
        port=0,
        key_file=str(fleet.member_path(Role.STATION, 1)),
        origin=ORIGIN,
        landing_pads=RETURNS.pad_layout,
    )
    with GroundStation(cfg) as station:
        station.endpoint = ep
        yield station


@pytest.fixture(scope="module")
def agent(fleet, gcs):
    argv = [*keyed_agent_argv(fleet, 1), "--fleet", FLEET, "--connect", gcs.endpoint]
    argv += ["--start-ne-m=20,20", "--no-gcs-failsafe", *PADS_ARGV]
    with ChildGroup(prefix=[sys.executable], cwd=REPO, env=python_env(REPO), grace_s=0.0) as procs:
        proc = procs.start(*argv)
        assert wait_until(lambda: 1 in gcs.fleet.positions(), 60), proc.output()
        yield proc


@pytest.fixture(scope="module")
def page(gcs, agent):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        pg = browser.new_page(viewport={"width": 1200, "height": 800})
        pg.set_default_timeout(60_000)
        pg.goto(gcs.url)
        pg.get_by_role("button", name="Arm kill").wait_for()
        pg.locator("canvas").first.wait_for()
        (client,) = gcs.server.get_clients().values()
        pg.get_by_text("Edit fleet plan", exact=True).click(force=True)
        choose(pg, GROUND_CLICK, CLICK_ADD)
        assert wait_until(lambda: gcs.plan_editors[client.client_id]._click is not None, 10)
        # Position first: viser moves look_at along with a new position.
        client.camera.position = (6.0, -14.0, 40.0)
        client.camera.look_at = (6.0, 6.0, 0.0)  # scene x east, y north, z up
        assert wait_until(
            lambda: (
                abs(client.camera.position[2] - 40.0) < 0.1
                and abs(client.camera.look_at[1] - 6.0) < 0.1
            ),
            10,
        ), (client.camera.position, client.camera.look_at)
        time.sleep(1.0)  # a rendered frame at the new pose
        pg.client = client
        yield pg
        browser.close()


def _click_corners(page, gcs, corners) -> None:
    editor = gcs.plan_editors[page.client.client_id]
    before = len(editor.draft.corners_ne_m) if editor.draft else 0
    for k, (n, e) in enumerate(corners, start=1):
        page.mouse.click(*screen_xy(page, page.client, (n, e, 0.0)))
        assert wait_until(
            lambda k=k: editor.draft is not None and len(editor.draft.corners_ne_m) == before + k,
            10,
        )


def _press(page, name: str) -> None:
    page.get_by_role("button", name=name, exact=True).click(force=True)


def _goto(gcs, n: float, e: float, alt: float):
    cmd = Command.goto_local(n, e, -alt, nonce=new_nonce(), stamp_ns=0, targets=(1,))
    return gcs.mesh.send_command(cmd, timeout_s=5).outcomes[1]


def test_a_zone_drawn_in_the_browser_reaches_the_agent_which_flies_around_it(page, gcs):
    editor = gcs.plan_editors[page.client.client_id]
    _click_corners(page, gcs, ZONE_NE_M)
    clicked = shapely.Polygon(editor.draft.corners_ne_m)
    # Where the clicks met the ground: the corners, to the screen's pixel (~0.1 m here).
    assert clicked.symmetric_difference(shapely.Polygon(ZONE_NE_M)).area < 10.0, clicked
    page.get_by_label(ZONE_NAME, exact=True).fill("depot")
    _press(page, "Close zone")
    page.get_by_text("zone 1 ('depot') added (4 corners)", exact=False).first.wait_for()
    _press(page, "Sign and push plan")
    page.get_by_text("pushed", exact=False).first.wait_for()
    plan = gcs.plan_view.sync.plan
    assert plan is not None and plan.signer_id == 1 and [z.name for z in plan.keep_out] == ["depot"]
    # The agent holds the new version: it refuses a goto into the zone, with the reason.
    deadline = time.monotonic() + 15
    while "keep-out" not in (out := _goto(gcs, 6, 6, 5)).reason:
        assert time.monotonic() < deadline, out
        time.sleep(0.2)
    assert out.status is OutcomeStatus.REJECTED and out.reason == (
        "target inside keep-out zone 'depot'"
    )
    # The command log lists the push, with what changed.
    assert wait_until(lambda: f'data-plan="{plan.version}"' in gcs.command_log_html.content, 10)
    assert "zone 1 (&#x27;depot&#x27;) added (4 corners)" in gcs.command_log_html.content
    # Flown across the zone's corner, the agent's route is drawn around it.
    takeoff = Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=0, targets=(1,))
    tk = gcs.mesh.send_command(takeoff, timeout_s=5)
    assert tk.outcomes[1].status is OutcomeStatus.ACCEPTED, tk
    assert wait_until(lambda: _goto(gcs, -8, -8, 3).status is OutcomeStatus.ACCEPTED, 30)
    assert wait_until(lambda: 1 in gcs.plan_view.routes.drawn, 10)
    route = gcs.plan_view.routes.drawn[1]
    assert len(route) >= 3 and shapely.LineString(route[:, :2]).distance(clicked) > 1.5


def test_a_self_crossing_zone_is_refused_with_its_reason_and_a_corner_moves(page, gcs):
    held = gcs.plan_view.sync.plan
    _click_corners(page, gcs, BOW_TIE_NE_M)
    _press(page, "Close zone")
    page.get_by_text("is not a valid polygon: Self-intersection", exact=False).first.wait_for()
    assert page.locator("[data-plan-edit='error']").count() == 1
    _press(page, "Sign and push plan")
    page.get_by_text("refused: a zone or fence is half drawn", exact=False).first.wait_for()
    assert gcs.plan_view.sync.plan == held
    # A corner moved by number from the form, pushed: listed with the operator of the tab.
    _press(page, "Discard corners")
    for label, value in ((ZONE_NO, "1"), (CORNER_NO, "3"), (CORNER_N, "13"), (CORNER_E, "13")):
        page.get_by_label(label, exact=True).fill(value)
    _press(page, "Move corner")
    page.get_by_text("corner 3 moved to N 13, E 13", exact=False).first.wait_for()
    _press(page, "Sign and push plan")
    assert wait_until(lambda: gcs.plan_view.sync.plan.version > held.version, 10)
    assert gcs.plan_view.sync.plan.keep_out[0].vertices_ne_m[2] == (13.0, 13.0)
    version = gcs.plan_view.sync.plan.version
    line = f"this station (operator): plan v{version}: zone 1 (&#x27;depot&#x27;) corner 3 moved"
    assert wait_until(lambda: line in gcs.command_log_html.content, 10)
    # A ground click moves the corner the fields name (drawn in the draft, not pushed).
    choose(page, GROUND_CLICK, CLICK_MOVE)
    editor = gcs.plan_editors[page.client.client_id]
    assert wait_until(lambda: editor.ground.value == CLICK_MOVE, 10)
    page.mouse.click(*screen_xy(page, page.client, (15.0, 15.0, 0.0)))
    moved = lambda: editor.draft and editor.draft.geometry.keep_out[0].vertices_ne_m[2]  # noqa: E731
    assert wait_until(lambda: moved() and abs(moved()[0] - 15.0) < 0.5, 10), editor.draft
    page.get_by_text("zone 1 ('depot') corner 3 moved to N 1", exact=False).first.wait_for()
    _press(page, "Reset draft")
    assert wait_until(lambda: editor.draft is None, 10)


def test_a_fence_drawn_and_a_corner_moved_in_the_browser_bounds_the_agents_gotos(page, gcs):
    editor = gcs.plan_editors[page.client.client_id]
    held = gcs.plan_view.sync.plan
    assert held.fence is None
    # The agent arrived where the first test sent it, well inside the fence to come.
    assert wait_until(lambda: max(abs(c + 8.0) for c in gcs.fleet.positions()[1][:2]) < 2.0, 60)
    choose(page, GROUND_CLICK, CLICK_ADD)
    assert wait_until(lambda: editor.ground.value == CLICK_ADD, 10)
    page.client.camera.position = (7.5, -30.0, 70.0)
    page.client.camera.look_at = (7.5, 7.5, 0.0)
    assert wait_until(lambda: abs(page.client.camera.position[2] - 70.0) < 0.1, 10)
    time.sleep(1.0)  # a rendered frame at the new pose
    _click_corners(page, gcs, FENCE_NE_M)
    clicked = shapely.Polygon(editor.draft.corners_ne_m)
    assert clicked.symmetric_difference(shapely.Polygon(FENCE_NE_M)).area < 30.0, clicked
    _press(page, "Close fence")
    page.get_by_text("fence drawn (4 corners)", exact=False).first.wait_for()
    assert "zone 0: the fence, 4 corners (0.1 to 0.4)" in editor.draft_html.content
    for label, value in ((ZONE_NO, "0"), (CORNER_NO, "2"), (CORNER_N, "-15"), (CORNER_E, "10")):
        page.get_by_label(label, exact=True).fill(value)
    _press(page, "Move corner")
    page.get_by_text("fence corner 2 moved to N -15, E 10", exact=False).first.wait_for()
    labels = {h.name: h for h in editor._drawn if h.name.startswith(f"{DRAFT_PATH}/corners/0_")}
    assert labels[f"{DRAFT_PATH}/corners/0_2"].text == "0.2"  # numbered in the tab's view
    assert np.allclose(labels[f"{DRAFT_PATH}/corners/0_2"].position[:2], (10.0, -15.0))  # E, N
    _press(page, "Sign and push plan")
    assert wait_until(lambda: gcs.plan_view.sync.plan.version > held.version, 10)
    fence = gcs.plan_view.sync.plan.fence
    assert fence is not None and fence.vertices_ne_m[1] == MOVED_NE_M, fence
    # The agent holds it once its polygon replaces the 500 m circle for a far goto.
    deadline = time.monotonic() + 15
    while "fence" not in (out := _goto(gcs, 0, 600, 5)).reason or "500" in out.reason:
        assert time.monotonic() < deadline, out
        time.sleep(0.2)
    assert out.reason == "target outside the fence"
    # Inside the fence as clicked, outside it with the corner moved: refused, with the reason.
    out = _goto(gcs, -10, 20, 5)
    assert out.status is OutcomeStatus.REJECTED and out.reason == "target outside the fence", out
    version = gcs.plan_view.sync.plan.version
    line = f"plan v{version}: fence drawn (4 corners); fence corner 2 moved to N -15, E 10"
    assert wait_until(lambda: line in gcs.command_log_html.content, 10)


def test_a_rally_point_clicked_and_moved_in_the_browser_is_where_the_agent_returns(page, gcs):
    editor = gcs.plan_editors[page.client.client_id]
    held = gcs.plan_view.sync.plan
    assert held.rally == ()
    choose(page, GROUND_CLICK, CLICK_RALLY)
    assert wait_until(lambda: editor.ground.value == CLICK_RALLY, 10)
    # Inside the zone: refused with check_geometry's words, the draft without it.
    page.mouse.click(*screen_xy(page, page.client, (6.0, 6.0, 0.0)))
    page.get_by_text("keep-out zone 'depot' covers a rally point", exact=False).first.wait_for()
    assert editor.draft is None or editor.draft.geometry.rally == ()
    page.mouse.click(*screen_xy(page, page.client, (21.0, 1.0, 0.0)))
    page.get_by_text("rally point 1 added at N 2", exact=False).first.wait_for()
    (clicked,) = editor.draft.geometry.rally
    assert abs(clicked.n_m - 21.0) < 0.5 and abs(clicked.e_m - 1.0) < 0.5, clicked
    for label, value in ((RALLY_NO, "1"), (CORNER_N, "20"), (CORNER_E, "0")):
        page.get_by_label(label, exact=True).fill(value)
    _press(page, MOVE_RALLY)
    page.get_by_text("rally point 1 moved to N 20, E 0", exact=False).first.wait_for()
    assert "rally 1 at N 20, E 0" in editor.draft_html.content
    label = next(h for h in editor._drawn if h.name == f"{DRAFT_PATH}/rally/1/label")
    assert label.text == "rally 1"  # numbered in the tab's view
    _press(page, "Sign and push plan")
    assert wait_until(lambda: gcs.plan_view.sync.plan.version > held.version, 10)
    plan = gcs.plan_view.sync.plan
    assert [(r.n_m, r.e_m, r.name) for r in plan.rally] == [(*RALLY_NE_M, "")]
    assert plan.fence == held.fence and plan.keep_out == held.keep_out
    # The agent holds it: told to return, it heads for its pad at the rally point, not for
    # where it took off (its goal, as the station draws its route to it).
    spot = np.add(RALLY_NE_M, RETURNS.pad_ne_m(1))
    ret = Command(CommandKind.RETURN, nonce=new_nonce(), stamp_ns=0, targets=(1,))
    out = gcs.mesh.send_command(ret, timeout_s=5).outcomes[1]
    assert out.status is OutcomeStatus.ACCEPTED, out
    goal = lambda: gcs.plan_view.routes.drawn.get(1, np.zeros((1, 3)))[-1, :2]  # noqa: E731
    assert wait_until(lambda: np.hypot(*(goal() - spot)) < 0.5, 30), (goal(), spot)
    line = f"plan v{plan.version}: rally point 1 added at N 2"
    assert wait_until(lambda: line in gcs.command_log_html.content, 10)
