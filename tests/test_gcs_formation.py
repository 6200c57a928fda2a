"""The station's formation tab in real Chromium, on a real `covey demo` (3 sim agents, open mode)
with a second, in-process station: a shape pressed draws the assignment and sends nothing; a
form changed after the preview refuses to send; the previewed formation is sent as one goto per
vehicle, acked in the tab's matrix, and the vehicles end within 1 m of their slots."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import wait_until
from test_gcs_browser import CHROMIUM, CHROMIUM_ARGS, fill

from comms.schema import Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess
from groundstation.formation import FormationSpec, slots_ned_m
from groundstation.ops import cmd_cli
from groundstation.station import GcsConfig, GroundStation

pytestmark = [pytest.mark.browser, pytest.mark.e2e]
sync_api = pytest.importorskip("playwright.sync_api")


@pytest.fixture(scope="module")
def demo():
    with DemoProcess(["--vehicles", "3", "--port", "0", "--open-mode"]) as proc:
        yield proc


@pytest.fixture(scope="module")
def gcs(demo):
    mesh = MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))
    with GroundStation(GcsConfig(mesh=mesh, port=0, gcs_id=2)) as station:
        assert wait_until(lambda: set(station.fleet.positions()) >= {1, 2, 3}, 30)
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
    snap = gcs.fleet.snapshot(0, trails=False)
    return {v.vehicle_id: v.state.mode for v in snap.vehicles if v.state is not None}


def test_preview_then_send_a_circle(page, gcs, demo) -> None:
    assert cmd_cli(["takeoff", "5", "--to", "all", "--connect", demo.mesh_endpoint]) == 0
    assert wait_until(lambda: set(_modes(gcs).values()) == {Mode.HOLDING}, 40), _modes(gcs)
    page.get_by_role("tab", name="Formation").click()
    for label, value in {
        "Targets": "all",
        "Spacing (m)": "5",
        "Centre north (m)": "12",
        "Centre east (m)": "0",
        "Formation altitude above origin (m)": "6",
        "Heading (deg)": "0",
    }.items():
        fill(page, label, value)
    sent_before = gcs.last_result
    page.get_by_role("button", name="Circle", exact=True).click()
    page.get_by_text("Formation circle, 3 vehicles").wait_for()
    panel = next(iter(gcs.panels.values()))
    assert panel.formation.preview is not None and gcs.last_result is sent_before

    # The form changed after the preview: nothing is sent.
    fill(page, "Centre north (m)", "13")
    page.get_by_role("button", name="Send formation").click()
    page.get_by_text("the form changed since the preview").wait_for()
    assert gcs.last_result is sent_before

    # Slots closer than the separation: refused with the reason, nothing drawn or sent.
    fill(page, "Spacing (m)", "1")
    page.get_by_role("button", name="Circle", exact=True).click()
    page.get_by_text("closer than the 3 m separation").wait_for()
    assert panel.formation.preview is None

    fill(page, "Spacing (m)", "5")
    fill(page, "Centre north (m)", "12")
    page.get_by_role("button", name="Circle", exact=True).click()
    page.get_by_text("Formation circle, 3 vehicles").wait_for()
    page.get_by_role("button", name="Send formation").click()
    assert wait_until(
        lambda: gcs.last_result is not None and gcs.last_result.label.startswith("formation"), 20
    )
    done = gcs.last_result
    assert len(done.results) == 3 and all(r.ok for r in done.results), done
    page.locator("span[data-status='accepted']").nth(2).wait_for()
    slots = slots_ned_m(FormationSpec("circle", 5.0, (12.0, 0.0), 6.0), 3)

    def at_slots() -> bool:
        pos = gcs.fleet.positions()
        return all(min(np.linalg.norm(slots - np.array(pos[v]), axis=1)) <= 1.0 for v in (1, 2, 3))

    assert wait_until(at_slots, 60), gcs.fleet.positions()
