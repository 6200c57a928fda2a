"""The command panel: target selection, commands, the guarded kill, scenarios, and the ack matrix.

Every button builds its command from what the pressing tab's form showed at the moment of the
click (groundstation.browser_form), never from the server's copies of the fields, which viser's
client can leave stale. The values are validated (groundstation.inputs); anything wrong or
unknown is a clear message and nothing is sent. Sending happens on the station's command
worker, never on viser's callback thread.

One panel per browser tab (viser's client-scope GUI): each operator has their own form values,
their own ack matrix for their own commands, and their own kill guard. A kill is armed for the
targets the tab showed; only that tab's CONFIRM within the window kills exactly those vehicles,
and if its Targets changed in between, it disarms and says why. The fleet table, the command
log and the scene stay shared (groundstation.station).
"""

from __future__ import annotations

import html
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import viser

from comms.geo import GeoOrigin
from comms.plan import FleetPlan
from comms.schema import CommandKind
from groundstation import formation_panel, inputs, layout, mission_panel
from groundstation.browser_form import BrowserForms, FormSnapshot
from groundstation.dispatch import Dispatched, KillGuard
from groundstation.formation import FormationMemory
from groundstation.frames import ground_hit_ned, ned_to_scene
from groundstation.inputs import CommandRequest, InputError
from groundstation.tables import ack_matrix

Job = mission_panel.Job

# The labels of the inputs a command is built from (each tab reports these at every click, and
# each is the accessible name of its input). Altitudes are up, in metres, with their datum
# (groundstation.inputs): above the fleet origin for take-off and local gotos, AMSL for global.
TARGETS, TAKEOFF_ALT = "Targets", "Take-off altitude above origin (m)"
NORTH, EAST, ALT = "North (m)", "East (m)", "Altitude above origin (m)"
LAT, LON, GLOBAL_ALT = "Latitude (deg)", "Longitude (deg)", "Altitude AMSL (m)"
FORM_LABELS = (
    TARGETS,
    TAKEOFF_ALT,
    NORTH,
    EAST,
    ALT,
    LAT,
    LON,
    GLOBAL_ALT,
    *formation_panel.LABELS,
    *mission_panel.LABELS,
)
SELECT_HELP = "Click a vehicle in the 3D view to select it; shift-click adds it to Targets."


@dataclass(frozen=True)
class ArmedKill:
    """A kill armed in this tab, for the targets it showed."""

    targets_text: str
    targets: tuple[int, ...]


@dataclass(frozen=True)
class PanelHooks:
    """What the panel needs from the station (kept as callables so it can be tested alone)."""

    known_ids: Callable[[], set[int]]
    """Ids of the vehicles the station knows (present or with a state)."""
    dispatch: Callable[[str, Sequence[Job], Callable[[Dispatched], None], int | None], None]
    """Send these (request, targets) jobs in order for a tab (its client id), then hand the
    answers to the callback."""
    scenario: Callable[[str], list[Job]]
    """Build the jobs of a named scenario ("swap", "random")."""
    now_s: Callable[[], float]
    """Monotonic seconds (the kill window is measured with it)."""
    positions: Callable[[], Mapping[int, tuple[float, float, float]]] = dict
    """The vehicles' latest NED positions (formations are assigned from them)."""
    pos_sigmas: Callable[[], Mapping[int, float]] = dict
    """The vehicles' latest reported position 1-sigma (formation slots are checked against the
    zone clearance their filters keep at it)."""
    formations: FormationMemory = field(default_factory=FormationMemory)
    """The station's remembered formation assignments (a moved formation keeps its slots)."""
    separation_m: float = 3.0
    """Formation slots closer than this are refused; the fleet's separation the vehicles'
    filters keep (their zone clearance follows from it)."""
    fleet_plan: Callable[[], FleetPlan | None] = lambda: None
    """The fleet plan whose fence and keep-out zones refuse formation slots."""


class CommandPanel:
    """The command panel of one browser tab."""

    def __init__(
        self,
        client: viser.ClientHandle,
        hooks: PanelHooks,
        forms: BrowserForms,
        origin: GeoOrigin,
        goto_limit_m: float,
        kill_window_s: float = 5.0,
    ) -> None:
        self.client = client
        self.hooks = hooks
        self.forms = forms
        self.goto_limit_m = goto_limit_m
        self.kill_guard = KillGuard(kill_window_s)
        self._armed: ArmedKill | None = None
        self._ground_click: Callable | None = None
        gui = client.gui
        # The kill in a window of its own, floating over the 3D view: nothing opened or scrolled
        # in the control panel can push it out of view (groundstation.layout).
        self.kill_panel = gui.add_panel(order=layout.KILL)
        with self.kill_panel.add_tab("Kill", viser.Icon.SKULL):
            self.kill_arm = gui.add_button(
                "Arm kill", color="orange", icon=viser.Icon.ALERT_TRIANGLE
            )
            self.kill_confirm = gui.add_button(
                "CONFIRM KILL", color="red", disabled=True, icon=viser.Icon.SKULL
            )
            self.kill_note = gui.add_html(
                _note("Motors off, vehicles fall. Arms for the Targets in the panel.")
            )
        self.kill_panel.float(**layout.KILL_WINDOW)
        # Messages and acks next: the operator must see what happened without scrolling.
        self.message = gui.add_html("", order=layout.MESSAGES)
        self.acks = gui.add_html("", order=layout.MESSAGES + 0.1)
        with gui.add_folder("Command", order=layout.COMMAND):
            self.targets = gui.add_text(
                TARGETS, "all", hint="'all', an id, or ids like 1,2,5 or 1-4. " + SELECT_HELP
            )
            gui.add_html(f"<div style='font-size:0.75em;color:#555'>{SELECT_HELP}</div>")
            self.alt = gui.add_number(
                TAKEOFF_ALT, 5.0, step=0.5, hint="Metres, up, above the fleet origin (N 0, E 0)."
            )
            self.takeoff = gui.add_button("Takeoff", icon=viser.Icon.ARROW_BAR_UP)
            self.simple = gui.add_button_group("Now", ("Land", "Hold", "Return"))
        tabs = gui.add_tab_group(order=layout.GOTO)
        with tabs.add_tab("Goto local", viser.Icon.TARGET):
            self.north = gui.add_number(NORTH, 0.0, step=0.5, hint="Metres north of the origin.")
            self.east = gui.add_number(EAST, 0.0, step=0.5, hint="Metres east of the origin.")
            self.up = gui.add_number(
                ALT, 5.0, step=0.5, hint="Metres, up, above the fleet origin (as take-off)."
            )
            self.pick = gui.add_checkbox("Click ground to set N/E", False)
            self.goto = gui.add_button("Goto local", icon=viser.Icon.TARGET)
        with tabs.add_tab("Goto global", viser.Icon.WORLD):
            self.lat = gui.add_number(LAT, origin.lat_deg, step=1e-5)
            self.lon = gui.add_number(LON, origin.lon_deg, step=1e-5)
            self.galt = gui.add_number(
                GLOBAL_ALT,
                origin.alt_m + 5.0,
                step=0.5,
                hint=f"Metres above mean sea level; the fleet origin is at {origin.alt_m:g} m AMSL.",
            )
            self.goto_global = gui.add_button("Goto global", icon=viser.Icon.WORLD)
        with tabs.add_tab("Scenarios", viser.Icon.ROUTE):
            self.scenarios = gui.add_button_group("Run", ("Swap", "Random goals"))
        with tabs.add_tab("Formation", viser.Icon.GRID_DOTS):
            self.formation = formation_panel.FormationSection(
                client,
                read_form=self._form,
                targets=self._targets,
                positions=hooks.positions,
                pos_sigmas=hooks.pos_sigmas,
                memory=hooks.formations,
                separation_m=hooks.separation_m,
                plan_of_fleet=hooks.fleet_plan,
                send=lambda label, jobs: hooks.dispatch(
                    label, jobs, self.show_result, client.client_id
                ),
                say=self.say,
                goto_limit_m=goto_limit_m,
                targets_label=TARGETS,
            )
        with tabs.add_tab("Mission", viser.Icon.ROUTE_2):
            self.mission = mission_panel.MissionSection(
                client,
                read_form=self._form,
                targets=self._targets,
                send=lambda label, jobs: hooks.dispatch(
                    label, jobs, self.show_result, client.client_id
                ),
                say=self.say,
                origin=origin,
                goto_limit_m=goto_limit_m,
            )
        self._wire()

    # -- wiring --------------------------------------------------------------------------
    def _wire(self) -> None:
        self.takeoff.on_click(
            lambda e: self._send(e, "Takeoff", lambda f: inputs.takeoff(f.get(TAKEOFF_ALT)))
        )
        kinds = {"Land": CommandKind.LAND, "Hold": CommandKind.HOLD, "Return": CommandKind.RETURN}
        self.simple.on_click(
            lambda e: self._send(e, e.target.value, lambda _f: inputs.simple(kinds[e.target.value]))
        )
        self.goto.on_click(
            lambda e: self._send(
                e,
                "Goto local",
                lambda f: inputs.goto_local(
                    f.get(NORTH), f.get(EAST), f.get(ALT), self.goto_limit_m
                ),
            )
        )
        self.goto_global.on_click(
            lambda e: self._send(
                e,
                "Goto global",
                lambda f: inputs.goto_global(f.get(LAT), f.get(LON), f.get(GLOBAL_ALT)),
            )
        )
        self.scenarios.on_click(
            lambda e: self._scenario("swap" if e.target.value == "Swap" else "random")
        )
        self.kill_arm.on_click(self.arm_kill)
        self.kill_confirm.on_click(self.confirm_kill)
        self.pick.on_update(lambda _: self._pick_mode(self.pick.value))

    def _pick_mode(self, on: bool) -> None:
        scene = self.client.scene
        if self._ground_click is not None:
            scene.remove_click_callback(self._ground_click)
            self._ground_click = None
        if not on:
            return

        @scene.on_click()
        def ground_click(event: viser.SceneClickEvent) -> None:
            hit = ground_hit_ned(event.ray_origin, event.ray_direction)
            if hit is None:
                self.say("That click does not hit the ground; aim below the horizon.", error=True)
                return
            # viser types GuiNumberHandle.value read-only (its props class); the setter is real
            self.north.value, self.east.value = round(hit[0], 1), round(hit[1], 1)  # type: ignore[misc]
            marker = ned_to_scene((hit[0], hit[1], 0.0))
            scene.add_icosphere(
                "/target",
                radius=0.4,
                color=(255, 200, 0),
                opacity=0.7,
                cast_shadow=False,
                receive_shadow=False,
                position=(float(marker[0]), float(marker[1]), float(marker[2])),
            )
            self.say(f"Goto target set to N {hit[0]:.1f} E {hit[1]:.1f}; press 'Goto local'.")

        self._ground_click = ground_click

    # -- actions -------------------------------------------------------------------------
    def select(self, vehicle_id: int, add: bool = False) -> None:
        """A click on a vehicle: it alone becomes the Targets; with `add` (shift-click), it
        joins the vehicles already there."""
        ids = {vehicle_id}
        if add:
            try:
                ids.update(inputs.targets(self.targets.value))
            except InputError:
                pass  # what was there is not a list of ids: the click starts a new one
        text = ",".join(map(str, sorted(ids)))
        self.targets.value = text  # type: ignore[misc]  # as above: viser's setter is real
        self.say(f"Targets: vehicle(s) {text} (shift-click adds, a click selects one).")

    def say(self, text: str, error: bool = False, kill_note: str | None = None) -> None:
        """Show `text` in the panel's message line, and `kill_note` (short) in the kill window,
        which stays in view when the panel is scrolled."""
        self.message.content = _note(text, error, data_msg=True)
        if kill_note is not None:
            self.kill_note.content = _note(kill_note, error)

    def _form(self, event: viser.GuiEvent, button: str) -> FormSnapshot:
        """What the pressing tab showed at the click (InputError if the station cannot know)."""
        return self.forms.read(event.client, button)

    def _targets(self, form: FormSnapshot) -> tuple[int, ...]:
        return inputs.targets(form.get(TARGETS), known=self.hooks.known_ids())

    def _send(
        self, event: viser.GuiEvent, button: str, build: Callable[[FormSnapshot], CommandRequest]
    ) -> None:
        try:
            form = self._form(event, button)
            req = build(form)
            targets = self._targets(form)
        except InputError as exc:
            self.say(str(exc), error=True)
            return
        self._dispatch(req, targets)

    def _dispatch(self, req: CommandRequest, targets: tuple[int, ...]) -> None:
        label = f"{req.describe()} → {_who(targets)}"
        self.say(f"Sending {label} …")
        self.hooks.dispatch(label, [(req, targets)], self.show_result, self.client.client_id)

    def _scenario(self, name: str) -> None:
        jobs = self.hooks.scenario(name)
        if not jobs:
            self.say(f"Scenario {name}: no vehicle with a known position.", error=True)
            return
        self.say(f"Scenario {name}: sending {len(jobs)} goals …")
        self.hooks.dispatch(
            f"scenario {name} ({len(jobs)} vehicles)", jobs, self.show_result, self.client.client_id
        )

    def arm_kill(self, event: viser.GuiEvent) -> None:
        try:
            form = self._form(event, "Arm kill")
            targets = self._targets(form)
        except InputError as exc:
            self.say(str(exc), error=True, kill_note="Not armed: check Targets in the panel.")
            return
        self._armed = ArmedKill(form.get(TARGETS), targets)
        self.kill_guard.arm(self.hooks.now_s())
        self.kill_confirm.disabled = False
        self.say(
            f"Kill ARMED for {_who(targets).replace('all vehicles', 'ALL vehicles')}: press "
            f"CONFIRM KILL within {self.kill_guard.window_s:g} s.",
            error=True,
            kill_note=f"ARMED, {_who(targets)}: confirm within {self.kill_guard.window_s:g} s",
        )

    def confirm_kill(self, event: viser.GuiEvent) -> None:
        armed, self._armed = self._armed, None
        in_window = self.kill_guard.confirm(self.hooks.now_s())
        self.kill_confirm.disabled = True
        if armed is None or not in_window:
            self.say(
                "Kill not armed (or the window passed): press 'Arm kill' first.",
                error=True,
                kill_note="Not armed: press Arm kill first.",
            )
            return
        try:
            form = self._form(event, "CONFIRM KILL")
        except InputError as exc:
            self.say(f"Kill disarmed: {exc}", error=True, kill_note="Disarmed; nothing sent.")
            return
        shown = form.values.get(TARGETS)
        if shown != armed.targets_text:
            self.say(
                f"Kill disarmed: Targets changed from {armed.targets_text!r} to {shown!r} after "
                "arming; nothing sent. Arm again for the vehicles you mean.",
                error=True,
                kill_note="Disarmed (Targets changed); nothing sent.",
            )
            return
        self._dispatch(inputs.simple(CommandKind.KILL), armed.targets)
        self.kill_note.content = _note(f"Kill sent to {_who(armed.targets)}.", error=True)

    def tick(self) -> None:
        """Called by the station's loop: closes an expired kill window."""
        if not self.kill_confirm.disabled and not self.kill_guard.armed(self.hooks.now_s()):
            self.kill_confirm.disabled = True
            self._armed = None
            self.say("Kill window expired; nothing was sent.", kill_note="Expired; nothing sent.")

    def show_result(self, done: Dispatched) -> None:
        self.acks.content = ack_matrix(done)
        self.say(
            f"Done: {done.label}" if not done.error else f"Failed: {done.error}",
            error=bool(done.error),
        )


def _note(text: str, error: bool = False, data_msg: bool = False) -> str:
    color, weight = ("#c5221f", "bold") if error else ("#333", "normal")
    tag = f" data-msg='{'error' if error else 'info'}'" if data_msg else ""
    return (
        f"<div{tag} style='color:{color};font-weight:{weight};font-size:0.82em'>"
        f"{html.escape(text)}</div>"
    )


def _who(targets: tuple[int, ...]) -> str:
    return "all vehicles" if not targets else "vehicle(s) " + ",".join(map(str, targets))
