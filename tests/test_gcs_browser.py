"""The ground station in real Chromium, driving a real `covey demo` (3 sim agents).

Every effect on the fleet is checked through the mesh (a test subscriber), not the DOM alone.
The tests run in file order on one demo and one page (module fixtures): table, input
validation, takeoff, goto, ground click, guarded kill, presence loss, screenshot.
"""

from __future__ import annotations

import io
import math
import os
import shutil
import signal
import threading
import time

import pytest

from comms import keys
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode, StateFlag, VehicleState
from comms.session import MeshConfig, open_session
from groundstation.demo_proc import DemoProcess

pytestmark = [pytest.mark.browser, pytest.mark.e2e]

CHROMIUM = shutil.which("chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
if CHROMIUM is None:
    pytest.skip(
        "Debian chromium is not installed (apt-get install chromium); CI installs it",
        allow_module_level=True,
    )
sync_api = pytest.importorskip("playwright.sync_api")


class StateLog:
    """Latest state of every vehicle, as a test subscriber on the mesh sees it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.latest: dict[int, VehicleState] = {}

    def __call__(self, state: VehicleState, _recv_ns: int) -> None:
        with self._lock:
            self.latest[state.vehicle_id] = state

    def get(self) -> dict[int, VehicleState]:
        with self._lock:
            return dict(self.latest)

    def wait(self, predicate, timeout_s: float, what: str) -> dict[int, VehicleState]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            states = self.get()
            if predicate(states):
                return states
            time.sleep(0.1)
        states = self.get()
        assert predicate(states), f"{what}: not seen within {timeout_s} s; states: {states}"
        return states


@pytest.fixture(scope="module")
def demo():
    with DemoProcess(["--vehicles", "3", "--port", "0"]) as proc:
        yield proc


@pytest.fixture(scope="module")
def states(demo):
    log = StateLog()
    with Mesh(MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))) as mesh:
        mesh.subscribe_states(log)
        log.wait(lambda s: set(s) >= {1, 2, 3}, 30.0, "states of vehicles 1-3")
        yield log


class CommandLog:
    """Every command sent to the fleet, as a silent queryable on the mesh sees it (it never
    replies, so the vehicles' acks are untouched)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.commands: list[Command] = []

    def __call__(self, query) -> None:
        cmd = Command.decode(query.payload.to_bytes())
        with self._lock:
            self.commands.append(cmd)

    def since(self, n: int) -> list[Command]:
        with self._lock:
            return self.commands[n:]

    def wait_new(self, n: int, timeout_s: float, what: str) -> Command:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            new = self.since(n)
            if new:
                return new[0]
            time.sleep(0.05)
        raise AssertionError(f"{what}: no command on the mesh within {timeout_s} s")


@pytest.fixture(scope="module")
def commands(demo):
    log = CommandLog()
    with open_session(MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))) as session:
        q = session.declare_queryable(keys.all_cmds("covey"), log, complete=False)
        time.sleep(0.5)  # let the queryable's declaration reach the station's router
        yield log
        q.undeclare()


@pytest.fixture(scope="module")
def page(demo):
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        pg = browser.new_page(viewport={"width": 1200, "height": 800})
        # Generous bounds: without a GPU, the first frames (shader compiles) can hold the page's
        # main thread for tens of seconds on a loaded machine.
        pg.set_default_timeout(60_000)
        pg.goto(demo.url)
        pg.get_by_role("button", name="Takeoff").wait_for()
        pg.locator("canvas").first.wait_for()
        pg.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        pg.gui_shown_s = time.monotonic()
        yield pg
        browser.close()


# Clicks use force=True: Playwright's "stable" check waits for animation frames, which software
# WebGL (no GPU here) makes slow; force still clicks the element where it is, with a real mouse.


def field(page, label: str):
    """The input of a viser GUI control, found by its visible label."""
    return page.locator(
        f"xpath=//label[normalize-space()='{label}']/ancestor::div[contains(@class,'mantine-Flex-root')][1]//input"
    )


def fill(page, label: str, value: str) -> None:
    # The station reads the form from the page at each click (groundstation/browser_form.py), so
    # nothing here waits for the edit to reach the server.
    field(page, label).fill(value)


TYPE_THEN_CLICK_JS = """([values, button]) => {
  // One task: every field is typed and the button clicked before the page renders a frame or
  // any timer runs, as a fast operator (or a busy browser) does.
  const setter = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set;
  for (const [label, value] of Object.entries(values)) {
    const el = [...document.querySelectorAll('label')].find(l => l.textContent.trim() === label)
      .closest('.mantine-Flex-root').querySelector('input');
    setter.call(el, value);
    el.dispatchEvent(new Event('input', {bubbles: true}));
  }
  [...document.querySelectorAll('button')].find(b => b.textContent.trim() === button).click();
}"""


def type_then_click(page, values: dict[str, str], button: str) -> None:
    page.evaluate(TYPE_THEN_CLICK_JS, [values, button])


def wait_ack(page, n: int, status: str = "accepted") -> None:
    page.locator(f"span[data-status='{status}']").nth(n - 1).wait_for()


def test_vehicles_appear_in_the_fleet_table(page):
    page.locator("tr[data-vehicle='3']").wait_for()
    assert page.locator("tr[data-vehicle]").count() == 3
    assert page.get_by_text("3 of 3 vehicles present").count() == 1


def test_bad_input_is_refused_in_the_gui_and_nothing_is_sent(page, states):
    fill(page, "Take-off altitude above origin (m)", "1000")
    page.get_by_role("button", name="Takeoff").click(force=True)
    msg = page.locator("[data-msg=error]")
    msg.wait_for()
    assert "outside the allowed range" in msg.inner_text()
    fill(page, "Targets", "7")
    page.get_by_role("button", name="Hold").click(force=True)
    page.get_by_text("Targets: no vehicle 7 in the fleet").wait_for()
    assert all(s.mode is Mode.LANDED for s in states.get().values())


def test_typed_values_and_a_click_in_the_same_frame_are_what_is_sent(page, states, commands):
    # The fields hold other values first (the station knows them), then the operator types new
    # ones and clicks before the page could send each edit: the command carries the typed ones.
    fill(page, "Targets", "2")
    fill(page, "Take-off altitude above origin (m)", "9")
    page.wait_for_timeout(300)
    n = len(commands.since(0))
    type_then_click(
        page, {"Targets": "1,3", "Take-off altitude above origin (m)": "4.5"}, "Takeoff"
    )
    cmd = commands.wait_new(n, 15.0, "takeoff typed and clicked in one frame")
    assert (cmd.kind, cmd.targets, cmd.params[0]) == (CommandKind.TAKEOFF, (1, 3), 4.5)
    states.wait(lambda s: s[1].armed and s[3].armed, 15.0, "vehicles 1 and 3 armed")
    assert not states.get()[2].armed, "vehicle 2 was not typed but took off"

    fill(page, "North (m)", "1")
    fill(page, "East (m)", "1")
    fill(page, "Altitude above origin (m)", "3")
    page.wait_for_timeout(300)
    n = len(commands.since(0))
    typed = {"Targets": "3", "North (m)": "-7.5", "East (m)": "6", "Altitude above origin (m)": "4"}
    type_then_click(page, typed, "Goto local")
    cmd = commands.wait_new(n, 15.0, "goto typed and clicked in one frame")
    assert (cmd.kind, cmd.targets, cmd.params) == (CommandKind.GOTO_LOCAL, (3,), (-7.5, 6.0, -4.0))
    states.wait(
        lambda s: math.dist(s[3].goal_ned_m[:2], (-7.5, 6.0)) < 0.1, 15.0, "vehicle 3's new goal"
    )
    # Land them again, so that the takeoff test below starts from a landed fleet.
    type_then_click(page, {"Targets": "all"}, "Land")
    states.wait(lambda s: all(v.mode is Mode.LANDED for v in s.values()), 60.0, "all landed")


def test_takeoff_to_all_makes_them_airborne(page, states):
    fill(page, "Targets", "all")
    fill(page, "Take-off altitude above origin (m)", "5")
    page.get_by_role("button", name="Takeoff").click(force=True)
    wait_ack(page, 3)
    states.wait(
        lambda s: all(v.armed and -v.pos_ned_m[2] > 3.0 for v in s.values()) and len(s) == 3,
        30.0,
        "all three airborne above 3 m",
    )
    # The shared command log says so, per vehicle, once each holds at its altitude.
    takeoff = page.locator("[data-command]", has_text="takeoff to 5.0 m above origin").first
    for vid in (1, 2, 3):
        takeoff.locator(f"span[data-vehicle='{vid}'][data-answer='done']").wait_for()
    assert "reached" in takeoff.inner_text()


def test_a_keyless_command_query_is_counted_never_logged(page, demo, commands):
    # Issue 34: a process without keys queries the fleet's command keys with a kill that
    # claims to come from station 1. The keyed station logs none of it, as any of its
    # commands; one line counts the attempts.
    with open_session(MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))) as attacker:
        for n in range(1, 61):
            kill = Command(CommandKind.KILL, nonce=n, stamp_ns=time.time_ns(), source_id=1)
            for _ in attacker.get(keys.all_cmds("covey"), payload=kill.encode(), timeout=0.3):
                pass
    line = page.locator("[data-refused-commands]")
    line.wait_for()
    page.wait_for_function(
        "() => +document.querySelector('[data-refused-commands]').dataset.refusedCommands >= 60"
    )
    assert "unsigned command" in line.inner_text()
    assert page.locator("[data-command]", has_text="kill").count() == 0


def test_goto_from_the_form_moves_a_vehicle(page, states):
    now = states.get()
    start = now[2].pos_ned_m
    # 6 m away from the other vehicles, so the policy has no neighbour to swerve around.
    others = [s.pos_ned_m for vid, s in now.items() if vid != 2]
    away = (
        start[0] - sum(p[0] for p in others) / len(others),
        start[1] - sum(p[1] for p in others) / len(others),
    )
    norm = math.hypot(*away) or 1.0
    target = (round(start[0] + 6.0 * away[0] / norm, 1), round(start[1] + 6.0 * away[1] / norm, 1))
    fill(page, "Targets", "2")
    fill(page, "North (m)", f"{target[0]:g}")
    fill(page, "East (m)", f"{target[1]:g}")
    fill(page, "Altitude above origin (m)", "5")
    page.get_by_role("button", name="Goto local", exact=True).click(force=True)
    states.wait(
        lambda s: s[2].flags & StateFlag.HAS_GOAL and math.dist(s[2].goal_ned_m[:2], target) < 0.1,
        10.0,
        "vehicle 2 flying to the form's goal",
    )
    states.wait(
        lambda s: math.dist(s[2].pos_ned_m[:2], target) < math.dist(start[:2], target) - 2.0,
        30.0,
        "vehicle 2 closing on its goal by 2 m",
    )


def test_ground_click_places_the_goto_target(page):
    field(page, "Click ground to set N/E").check(force=True)
    north, east = field(page, "North (m)"), field(page, "East (m)")
    before = (north.input_value(), east.input_value())
    # below the horizon, left of the panel: the ground. On a loaded machine the first clicks can
    # land before the scene has drawn its ground; an operator clicks again, and so does this.
    for _ in range(10):
        page.mouse.click(380, 620)
        try:
            page.wait_for_function(
                "() => [...document.querySelectorAll('[data-msg]')].map(e => e.innerText)"
                ".join().includes('Goto target set to')",
                timeout=6_000,
            )
            break
        except sync_api.TimeoutError:
            continue
    assert (north.input_value(), east.input_value()) != before
    field(page, "Click ground to set N/E").uncheck(force=True)


def test_a_kill_armed_for_one_vehicle_is_disarmed_when_targets_change(page, states, commands):
    fill(page, "Targets", "1")
    page.get_by_role("button", name="Arm kill").click(force=True)
    page.get_by_text("Kill ARMED for vehicle(s) 1").wait_for()
    n = len(commands.since(0))
    type_then_click(page, {"Targets": "all"}, "CONFIRM KILL")
    page.get_by_text("Kill disarmed: Targets changed").wait_for()
    time.sleep(1.0)
    assert [c for c in commands.since(n) if c.kind is CommandKind.KILL] == []
    assert all(s.mode is not Mode.KILLED for s in states.get().values())


def test_a_second_tab_cannot_confirm_a_kill_armed_in_the_first(page, states, commands, demo):
    # Tab 1 arms a kill for vehicle 3. Tab 2 (another operator, its own form and guard) types
    # Targets = all and presses CONFIRM: nothing is killed. Each tab has its own kill guard.
    other = page.context.browser.new_context(viewport={"width": 1200, "height": 800}).new_page()
    try:
        other.set_default_timeout(60_000)
        other.goto(demo.url)  # its own login (a new browser context has no cookie)
        other.get_by_role("button", name="Arm kill").wait_for()
        fill(page, "Targets", "3")
        page.get_by_role("button", name="Arm kill").click(force=True)
        page.get_by_text("Kill ARMED for vehicle(s) 3").wait_for()
        assert field(other, "Targets").input_value() == "all"  # tab 2 kept its own form
        sync_api.expect(other.get_by_role("button", name="CONFIRM KILL")).to_be_disabled()
        n = len(commands.since(0))
        fill(other, "Targets", "all")
        other.evaluate(  # press it the way a script could: disabled buttons ignore clicks
            "() => [...document.querySelectorAll('button')].find("
            "b => b.textContent.trim() === 'CONFIRM KILL').click()"
        )
        time.sleep(1.5)
        assert [c for c in commands.since(n) if c.kind is CommandKind.KILL] == []
        assert all(s.mode is not Mode.KILLED for s in states.get().values())
    finally:
        other.context.close()


def test_kill_needs_its_confirmation(page, states):
    fill(page, "Targets", "3")
    page.get_by_role("button", name="Arm kill").click(force=True)
    page.get_by_text("Kill ARMED").wait_for()
    # One click alone never kills: vehicle 3 keeps flying (checked on the mesh for a while).
    armed_at = time.monotonic()
    while time.monotonic() - armed_at < 1.5:
        assert states.get()[3].mode is not Mode.KILLED
        time.sleep(0.1)
    page.get_by_role("button", name="CONFIRM KILL").click(force=True)
    states.wait(lambda s: s[3].mode is Mode.KILLED, 10.0, "vehicle 3 killed after confirmation")
    assert states.get()[1].mode is not Mode.KILLED and states.get()[2].mode is not Mode.KILLED
    sync_api.expect(page.get_by_role("button", name="CONFIRM KILL")).to_be_disabled()


def test_a_lost_vehicle_is_shown_lost(page, demo):
    os.kill(demo.agent_pids[1], signal.SIGKILL)  # its liveliness token vanishes with its TCP link
    t0 = time.monotonic()
    page.locator("tr[data-vehicle='1']", has_text="LOST").wait_for(timeout=10_000)
    print(f"vehicle 1 shown LOST {time.monotonic() - t0:.2f} s after its agent was killed")
    page.get_by_text("2 of 3 vehicles present").wait_for()


def test_screenshot_of_the_scene_is_not_blank(page, tmp_path_factory):
    import numpy as np
    from PIL import Image

    # The WebGL canvas fades in after the GUI; by now it has (the earlier steps take > 5 s).
    page.wait_for_timeout(max(0.0, 5.0 - (time.monotonic() - page.gui_shown_s)) * 1000)
    path = tmp_path_factory.mktemp("gcs") / "gcs.png"
    png = page.screenshot(path=str(path))
    img = Image.open(io.BytesIO(png)).convert("L")
    scene = np.asarray(
        img.crop((0, 150, 800, 800)), dtype=np.float64
    )  # the 3D view, left of the panel
    variance = float(scene.var())
    assert variance > 50.0, f"scene looks blank (variance {variance:.1f}); screenshot at {path}"
