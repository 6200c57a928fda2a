"""Missions from the browser station, in real Chromium, on a real `covey demo` (2 sim agents,
open mode) and an in-process station: a mission file loaded through the Mission tab's upload
button is drawn, uploaded to the Targets (each vehicle's ack in the tab's matrix, its route in
the shared scene, its progress in the fleet table), and started, paused, resumed and aborted
from the same tab; a file that cannot be flown says why and nothing is sent."""

from __future__ import annotations

import json

import pytest
from conftest import wait_until
from test_gcs_browser import CHROMIUM, CHROMIUM_ARGS

from comms.commands import OutcomeStatus
from comms.schema import Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess
from groundstation.panel import TAKEOFF_ALT, TARGETS
from groundstation.station import GcsConfig, GroundStation

pytestmark = [pytest.mark.browser, pytest.mark.e2e]
sync_api = pytest.importorskip("playwright.sync_api")

ROUTE = {
    "mission_id": 4,
    "items": [
        {"kind": "waypoint", "north_m": 25, "east_m": -6, "alt_m": 5},
        {"kind": "waypoint", "north_m": 25, "east_m": 6, "alt_m": 5, "hold_s": 2},
        {"kind": "land"},
    ],
}


@pytest.fixture(scope="module")
def demo():
    with DemoProcess(["--vehicles", "2", "--port", "0", "--open-mode"]) as proc:
        yield proc


@pytest.fixture(scope="module")
def gcs(demo):
    mesh = MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))
    with GroundStation(GcsConfig(mesh=mesh, port=0, gcs_id=2)) as station:
        assert wait_until(lambda: set(station.fleet.positions()) >= {1, 2}, 30)
        yield station


@pytest.fixture(scope="module")
def page(gcs):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        pg = browser.new_page(viewport={"width": 1200, "height": 900})
        pg.set_default_timeout(60_000)
        pg.goto(gcs.url)
        pg.get_by_role("button", name="Arm kill").wait_for()
        yield pg
        browser.close()


def _modes(gcs) -> dict[int, Mode]:
    return {v.vehicle_id: v.state.mode for v in gcs.fleet.snapshot(0).vehicles if v.state}


def _done(gcs, label: str):
    ok = wait_until(lambda: gcs.last_result is not None and label in gcs.last_result.label, 30)
    assert ok, gcs.last_result
    return gcs.last_result


def _file_input(page):
    """The hidden file input of the Mission tab's upload button."""
    return page.locator(
        "xpath=//button[normalize-space()='Load mission file']/preceding-sibling::input[@type='file']"
    )


def _press(page, name: str) -> None:
    page.get_by_role("button", name=name, exact=True).click(force=True)


def test_a_mission_file_from_the_browser_flies_and_is_controlled(page, gcs, tmp_path):
    bad = tmp_path / "bad.plan"
    bad.write_text(json.dumps({"items": [{"kind": "waypoint", "north_m": 1, "alt_m": -2}]}))
    page.get_by_role("tab", name="Mission").click()
    _file_input(page).set_input_files(str(bad))
    page.get_by_text("item 1: needs 'east_m'", exact=False).first.wait_for()  # said why
    assert page.locator("[data-msg='error']").count() >= 1
    good = tmp_path / "route.json"
    good.write_text(json.dumps(ROUTE))
    _file_input(page).set_input_files(str(good))
    page.get_by_text("Loaded route.json: mission 4, 3 items", exact=False).first.wait_for()

    page.get_by_label(TARGETS, exact=True).fill("1,2")
    _press(page, "Upload mission")
    done = _done(gcs, "mission 4 upload")
    assert done.results and done.results[0].by_status(OutcomeStatus.ACCEPTED) == [1, 2], done
    assert wait_until(lambda: gcs.scene.route_nodes.keys() == {1, 2}, 10), gcs.routes
    page.locator("[data-mission='0/3']").first.wait_for()  # the fleet table: loaded, 3 items

    _press(page, "Start")
    started = _done(gcs, "mission start")
    assert all("take off first" in o.reason for o in started.results[0].outcomes.values())
    page.get_by_label(TAKEOFF_ALT, exact=True).fill("4")
    _press(page, "Takeoff")
    assert wait_until(lambda: set(_modes(gcs).values()) == {Mode.HOLDING}, 60), _modes(gcs)
    _press(page, "Start")
    assert _done(gcs, "mission start").results[0].ok
    assert wait_until(lambda: set(_modes(gcs).values()) == {Mode.MISSION}, 10), _modes(gcs)
    page.locator("[data-mission='1/3']").first.wait_for()

    page.get_by_label(TARGETS, exact=True).fill("1")
    _press(page, "Pause")
    assert _done(gcs, "mission pause").results[0].ok
    assert wait_until(lambda: _modes(gcs) == {1: Mode.HOLDING, 2: Mode.MISSION}, 10)
    _press(page, "Resume")
    assert _done(gcs, "mission resume").results[0].ok
    assert wait_until(lambda: _modes(gcs)[1] is Mode.MISSION, 10)
    page.get_by_label(TARGETS, exact=True).fill("all")
    _press(page, "Abort")
    assert _done(gcs, "mission abort").results[0].ok
    assert wait_until(lambda: set(_modes(gcs).values()) == {Mode.HOLDING}, 10), _modes(gcs)
    page.locator("[data-mission='0/3']").first.wait_for()  # progress dropped, mission kept
