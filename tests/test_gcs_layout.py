"""The station's layout in real Chromium, on a real `covey demo` (2 sim agents, open mode) with a
second, in-process station whose camera the test sets: the inputs have accessible names, the log
and the events are open from the start, the kill stays in view, the fence is labelled, a click
and a shift-click on vehicles fill Targets, and the log says "done" once a take-off finished.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from conftest import wait_until
from test_gcs_browser import CHROMIUM, CHROMIUM_ARGS, field

from comms.schema import Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess
from groundstation.frames import ned_to_scene
from groundstation.panel import ALT, TAKEOFF_ALT, TARGETS
from groundstation.station import GcsConfig, GroundStation

pytestmark = [pytest.mark.browser, pytest.mark.e2e]
sync_api = pytest.importorskip("playwright.sync_api")
VIEWPORT = {"width": 1200, "height": 800}


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
        pg = browser.new_page(viewport=VIEWPORT)
        pg.set_default_timeout(60_000)
        pg.goto(gcs.url)
        pg.get_by_role("button", name="Arm kill").wait_for()
        pg.locator("canvas").first.wait_for()
        yield pg
        browser.close()


def in_view(page, locator) -> bool:
    box = locator.bounding_box()
    return box is not None and box["y"] >= 0 and box["y"] + box["height"] <= VIEWPORT["height"]


def test_inputs_have_accessible_names_and_the_panels_start_open(page, gcs):
    for label in (TARGETS, TAKEOFF_ALT, ALT):
        page.get_by_label(label, exact=True).wait_for()
        assert page.get_by_label(label, exact=True).count() == 1, label
    page.get_by_label(TARGETS, exact=True).fill("1,2")
    assert field(page, TARGETS).input_value() == "1,2"
    page.get_by_label(TARGETS, exact=True).fill("all")
    # The log and the events are open and say that nothing happened yet.
    page.get_by_text("no commands yet", exact=False).wait_for(state="visible")
    page.get_by_label("Event kind", exact=True).wait_for(state="visible")
    page.get_by_text("shift-click adds it to Targets", exact=False).first.wait_for(state="visible")
    # The fence is labelled where it is drawn (viser draws labels in WebGL, not in the DOM).
    assert gcs.scene.fence_label.text == "geofence 50 m"


def screen_xy(page, client, ned_m) -> tuple[float, float]:
    """Where a NED point appears on the page: the client's own camera (as it reported it to the
    server), a pinhole with its vertical field of view, over the canvas."""
    box = page.locator("canvas").first.bounding_box()
    cam = client.camera
    pos, look, up = (np.asarray(v, float) for v in (cam.position, cam.look_at, cam.up_direction))
    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    d = np.asarray(ned_to_scene(tuple(float(x) for x in ned_m)), float) - pos
    x, y, z = d @ right, d @ true_up, d @ fwd
    t = math.tan(cam.fov / 2.0)
    ndc_x, ndc_y = x / (z * t * box["width"] / box["height"]), y / (z * t)
    return box["x"] + (ndc_x + 1) / 2 * box["width"], box["y"] + (1 - ndc_y) / 2 * box["height"]


def test_a_click_selects_a_vehicle_and_a_shift_click_adds_one(page, gcs):
    (client,) = gcs.server.get_clients().values()
    client.camera.look_at = (0.0, 0.0, 0.0)
    client.camera.position = (0.0, -9.0, 14.0)
    assert wait_until(lambda: abs(client.camera.position[2] - 14.0) < 0.1, 10)
    time.sleep(1.0)  # a rendered frame at the new pose
    where = gcs.fleet.positions()
    page.mouse.click(*screen_xy(page, client, where[1]))
    page.wait_for_function(
        "(label) => [...document.querySelectorAll('input')].some("
        "i => i.getAttribute('aria-label') === label && i.value === '1')",
        arg=TARGETS,
    )
    page.keyboard.down("Shift")
    page.mouse.click(*screen_xy(page, client, where[2]))
    page.keyboard.up("Shift")
    page.wait_for_function(
        "(label) => [...document.querySelectorAll('input')].some("
        "i => i.getAttribute('aria-label') === label && i.value === '1,2')",
        arg=TARGETS,
    )


def test_the_log_says_done_once_the_take_off_finished(page, gcs):
    page.get_by_label(TARGETS, exact=True).fill("all")
    page.get_by_label(TAKEOFF_ALT, exact=True).fill("4")
    page.get_by_role("button", name="Takeoff").click(force=True)
    row = page.locator("[data-command]", has_text="takeoff to 4.0 m above origin").first
    for vid in (1, 2):
        row.locator(f"span[data-vehicle='{vid}'][data-answer='done']").wait_for(timeout=60_000)
    assert "this station" in row.inner_text()
    modes = {v.vehicle_id: v.mode for v in gcs.fleet.snapshot(time.time_ns()).vehicles}
    assert modes == {1: Mode.HOLDING, 2: Mode.HOLDING}


def test_the_kill_stays_in_view_when_the_log_grows_and_is_reopened(page):
    page.get_by_label(TARGETS, exact=True).fill("all")
    hold = page.get_by_role("button", name="Hold")
    for _ in range(6):  # a long log
        n = page.locator("[data-command]").count()
        hold.click(force=True)
        page.wait_for_function(
            "(n) => document.querySelectorAll('[data-command]').length > n", arg=n
        )
    header = page.get_by_text("Command log (every station)", exact=True)
    newest = page.locator("[data-command]").first
    header.click(force=True)  # closed, then open again
    newest.wait_for(state="hidden")
    header.click(force=True)
    newest.wait_for(state="visible")
    assert in_view(page, page.get_by_role("button", name="Arm kill"))
    assert in_view(page, page.get_by_role("button", name="CONFIRM KILL"))
    # Also with the panel scrolled to its end (the log's oldest entry).
    page.locator("[data-command]").last.scroll_into_view_if_needed()
    assert in_view(page, page.get_by_role("button", name="Arm kill"))
