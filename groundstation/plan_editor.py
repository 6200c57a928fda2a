"""Editing the fleet plan in the browser: one tab's "Edit fleet plan" folder and its draft.

The operator clicks a keep-out zone's or the fence's corners on the ground (Ground click: 'adds a
corner'), names a zone and presses 'Close zone', or presses 'Close fence' (the drawn fence
replaces the plan's); moves a corner by typing its place or by clicking the ground ('moves the
corner'), deletes a corner or a zone by number (zone number 0 is the fence), deletes the fence,
sets the fence's floor and ceiling; sets home ('Set home' at the typed north/east, or Ground
click: 'sets home'), adds a rally point ('Add rally point', or 'adds a rally point'), moves one
by its number ('Move rally point', or 'moves the rally point') or deletes it; then presses 'Sign
and push plan'. Each step is checked as it is taken (groundstation/plan_edit.py) and a refusal
is shown with its reason, the draft unchanged. The draft is drawn in this tab's own 3D view
(violet, each corner numbered zone.corner, the fence's 0.corner, home and 'rally k':
groundstation/plan_draft_view.py); the shared scene keeps showing the plan the fleet holds until
the push.

A push signs the draft with the station's key and pushes it as the next version through the path
an uploaded file takes (`PlanView.push_geometry`), listed in the command log with the operator's
name and the edits. A draft begun on a plan that another station has replaced since is refused
at push ('Reset draft' starts again from the fleet's plan).

Form state is per browser tab (viser's client GUI) and every button reads the values its tab
showed at the click (groundstation/browser_form.py), as the command panel does.
"""

from __future__ import annotations

import html
import threading
from collections.abc import Callable, Iterable

import viser

from comms.schema import StateFlag, VehicleState
from groundstation import plan_edit as pe
from groundstation.browser_form import BrowserForms, FormSnapshot
from groundstation.frames import ground_hit_ned
from groundstation.inputs import InputError, number
from groundstation.plan_draft_view import draft_html, draw_draft
from groundstation.plan_view import PlanView

GROUND_CLICK = "Ground click"
CLICK_OFF, CLICK_ADD, CLICK_MOVE = "does nothing", "adds a corner", "moves the corner"
CLICK_HOME, CLICK_RALLY = "sets home", "adds a rally point"
CLICK_MOVE_RALLY = "moves the rally point"
CLICK_MODES = (CLICK_OFF, CLICK_ADD, CLICK_MOVE, CLICK_HOME, CLICK_RALLY, CLICK_MOVE_RALLY)
ZONE_NAME = "New zone name"
ZONE_NO, CORNER_NO = "Zone number (0: fence)", "Corner number"
CORNER_N, CORNER_E = "North of origin (m)", "East of origin (m)"
"""Where a corner moves, or home or a rally point goes (typed)."""
FLOOR, CEILING = "Fence floor above origin (m)", "Fence ceiling above origin (m)"
RALLY_NAME, RALLY_NO = "New rally point name", "Rally point number"
POINT_ALT = "Home or rally point altitude above origin (m)"
LABELS = (
    ZONE_NAME, ZONE_NO, CORNER_NO, CORNER_N, CORNER_E, FLOOR, CEILING, RALLY_NAME, RALLY_NO,
    POINT_ALT,
)  # fmt: skip
"""The labelled inputs the editor's buttons read from the tab (groundstation/browser_form.py)."""
WHOLE = (ZONE_NO, CORNER_NO, RALLY_NO)
"""The fields that take a whole number."""
ZONE_BUTTONS = ("Close zone", "Close fence", "Discard corners")
CORNER_BUTTONS = ("Move corner", "Delete corner", "Delete zone", "Delete fence")
SET_HOME, ADD_RALLY = "Set home", "Add rally point"
MOVE_RALLY, DELETE_RALLY = "Move rally point", "Delete rally point"
RALLY_BUTTONS = (SET_HOME, ADD_RALLY, MOVE_RALLY, DELETE_RALLY)
SET_BAND, PUSH, RESET = "Set fence floor/ceiling", "Sign and push plan", "Reset draft"
MAX_COORD_INPUT_M = 100_000.0


def vehicle_points(states: Iterable[VehicleState]) -> tuple[pe.VehiclePoint, ...]:
    """Where each vehicle is, and where it flies to when it has a goal (NED -> up)."""
    out = []
    for s in states:
        n, e, d = s.pos_ned_m
        out.append(pe.VehiclePoint(s.vehicle_id, n, e, -d, is_target=False))
        if s.flags & StateFlag.HAS_GOAL:
            gn, ge, gd = s.goal_ned_m
            out.append(pe.VehiclePoint(s.vehicle_id, gn, ge, -gd, is_target=True))
    return tuple(out)


def _optional_alt(name: str, raw: str | None) -> float | None:
    if raw is None or not raw.strip():
        return None
    return number(name, raw.strip(), -MAX_COORD_INPUT_M, MAX_COORD_INPUT_M, " m")


class PlanEditor:
    """The plan editor of one browser tab."""

    def __init__(
        self,
        client: viser.ClientHandle,
        view: PlanView,
        forms: BrowserForms,
        *,
        states: Callable[[], Iterable[VehicleState]],
        operator: Callable[[], str | None],
        order: float,
    ) -> None:
        """`states()`: the vehicles' latest states (a new plan must not rule them out);
        `operator()`: who is logged in to this tab."""
        self.client, self.view, self.forms = client, view, forms
        self._states, self._operator = states, operator
        self._lock = threading.Lock()
        self.draft: pe.Draft | None = None
        """This tab's draft (None: not editing; read by tests)."""
        self._drawn: list = []
        self._click: Callable | None = None
        gui = client.gui
        with gui.add_folder("Edit fleet plan", order=order, expand_by_default=False):
            self.message = gui.add_html("")
            self.draft_html = gui.add_html(draft_html(None))
            self.ground = gui.add_dropdown(GROUND_CLICK, CLICK_MODES, initial_value=CLICK_OFF)
            self.zone_name = gui.add_text(ZONE_NAME, "", hint="What the operators call it.")
            self.zone_buttons = gui.add_button_group("Drawn corners", ZONE_BUTTONS)
            self.zone_no = gui.add_number(ZONE_NO, 1, min=pe.FENCE_NO, step=1)
            self.corner_no = gui.add_number(CORNER_NO, 1, min=1, step=1)
            self.corner_n = gui.add_number(CORNER_N, 0.0, step=0.5)
            self.corner_e = gui.add_number(CORNER_E, 0.0, step=0.5)
            self.corner_buttons = gui.add_button_group("Corner", CORNER_BUTTONS)
            self.floor = gui.add_text(FLOOR, "", hint="Metres, up; empty: no floor.")
            self.ceiling = gui.add_text(CEILING, "", hint="Metres, up; empty: no ceiling.")
            self.band_button = gui.add_button(SET_BAND)
            self.rally_name = gui.add_text(RALLY_NAME, "", hint="Optional; never 'home'.")
            self.rally_no = gui.add_number(RALLY_NO, 1, min=1, step=1)
            self.point_alt = gui.add_text(
                POINT_ALT, "", hint="Metres, up; empty: kept (0 for a new point)."
            )
            self.rally_buttons = gui.add_button_group("Home and rally points", RALLY_BUTTONS)
            self.push_button = gui.add_button(PUSH, color="green", icon=viser.Icon.SEND)
            self.reset_button = gui.add_button(RESET, icon=viser.Icon.TRASH)
        self.ground.on_update(lambda _e: self._click_mode(self.ground.value))
        self.zone_buttons.on_click(self._zone_pressed)
        self.corner_buttons.on_click(self._corner_pressed)
        self.band_button.on_click(self._band_pressed)
        self.rally_buttons.on_click(self._rally_pressed)
        self.push_button.on_click(self._push_pressed)
        self.reset_button.on_click(lambda _e: self.reset())

    # -- the steps (the buttons and the ground clicks call these) ------------------------------
    def _vehicles(self) -> tuple[pe.VehiclePoint, ...]:
        return vehicle_points(self._states())

    def _edit(self, step: Callable[[pe.Draft], pe.Draft]) -> bool:
        """Apply one step to the draft (begun from the fleet's plan); show it or why not."""
        with self._lock:
            base = (
                self.draft
                if self.draft is not None
                else pe.draft_of(self.view.sync.plan, self.view.separation_m, self.view.pads)
            )
            try:
                new = step(base)
            except pe.EditRefused as exc:
                self._say(f"refused: {exc}", error=True)
                return False
            self.draft = new
            self._show(new)
        self._say(new.edits[-1] if len(new.edits) > len(base.edits) else "draft updated")
        return True

    def add_corner(self, n_m: float, e_m: float) -> bool:
        ok = self._edit(lambda d: pe.add_corner(d, n_m, e_m))
        if ok and self.draft is not None:
            k = len(self.draft.corners_ne_m)
            self._say(
                f"corner {k} at N {n_m:.1f}, E {e_m:.1f}"
                + ("; press 'Close zone' or 'Close fence' when it is drawn" if k >= 3 else "")
            )
        return ok

    def close_zone(self, name: str) -> bool:
        return self._edit(lambda d: pe.close_zone(d, name, self._vehicles()))

    def close_fence(self) -> bool:
        return self._edit(lambda d: pe.close_fence(d, self._vehicles()))

    def discard_corners(self) -> bool:
        return self._edit(pe.discard_corners)

    def move_corner(self, zone_no: int, corner_no: int, n_m: float, e_m: float) -> bool:
        return self._edit(
            lambda d: pe.move_corner(d, zone_no, corner_no, n_m, e_m, self._vehicles())
        )

    def delete_corner(self, zone_no: int, corner_no: int) -> bool:
        return self._edit(lambda d: pe.delete_corner(d, zone_no, corner_no, self._vehicles()))

    def delete_zone(self, zone_no: int) -> bool:
        return self._edit(lambda d: pe.delete_zone(d, zone_no))

    def delete_fence(self) -> bool:
        return self._edit(pe.delete_fence)

    def set_fence_band(self, floor_alt_m: float | None, ceiling_alt_m: float | None) -> bool:
        return self._edit(
            lambda d: pe.set_fence_band(d, floor_alt_m, ceiling_alt_m, self._vehicles())
        )

    def set_home(self, n_m: float, e_m: float, alt_m: float | None = None) -> bool:
        return self._edit(lambda d: pe.set_home(d, n_m, e_m, alt_m))

    def add_rally(self, n_m: float, e_m: float, alt_m: float | None = None, name: str = "") -> bool:
        return self._edit(lambda d: pe.add_rally(d, n_m, e_m, alt_m, name))

    def move_rally(self, rally_no: int, n_m: float, e_m: float, alt_m: float | None = None) -> bool:
        return self._edit(lambda d: pe.move_rally(d, rally_no, n_m, e_m, alt_m))

    def delete_rally(self, rally_no: int) -> bool:
        return self._edit(lambda d: pe.delete_rally(d, rally_no))

    def reset(self) -> None:
        with self._lock:
            self.draft = None
            self._show(None)
        self._say("draft dropped: the panel shows the fleet's plan")

    def push(self, operator: str | None = None) -> str:
        """Sign the draft and push it as the fleet's next plan version; the line shown."""
        with self._lock:
            draft = self.draft
            held = self.view.sync.plan
            if draft is not None and draft.corners_ne_m:
                line = (
                    "refused: a zone or fence is half drawn (press 'Close zone', 'Close fence' "
                    "or 'Discard corners')"
                )
            elif draft is None or not draft.changed:
                line = "refused: nothing to push (edit the plan first)"
            elif (held.version if held else None) != draft.base_version:
                line = (
                    f"refused: the fleet plan is now v{held.version if held else '-'}, this "
                    f"draft began on v{draft.base_version or '-'} (press 'Reset draft')"
                )
            else:
                try:
                    before = pe.geometry_of(held)
                    geometry = pe.checked(
                        draft.geometry, self._vehicles(), before, draft.separation_m, draft.pads
                    )
                except pe.EditRefused as exc:
                    line = f"refused: {exc}"
                else:
                    line = self.view.push_geometry(geometry, draft.describe_edits(), operator)
                    if not line.startswith("refused"):
                        self.draft = None
                        self._show(None)
        self._say(line, error=line.startswith("refused"))
        return line

    # -- the buttons ---------------------------------------------------------------------------
    def _form(self, event: viser.GuiEvent, button: str) -> FormSnapshot | None:
        try:
            return self.forms.read(event.client, button)
        except InputError as exc:
            self._say(str(exc), error=True)
            return None

    def _numbers(self, form: FormSnapshot, *labels: str) -> list[float] | None:
        """The labelled fields' values; zone, corner and rally point numbers must be whole."""
        try:
            out = [
                number(label, form.get(label), -MAX_COORD_INPUT_M, MAX_COORD_INPUT_M)
                for label in labels
            ]
            for label, value in zip(labels, out, strict=True):
                if label in WHOLE and value != int(value):
                    raise InputError(f"{label}: enter a whole number, got {value:g}")
        except InputError as exc:
            self._say(str(exc), error=True)
            return None
        return out

    def _zone_pressed(self, event: viser.GuiEvent) -> None:
        button = event.target.value
        if button == "Discard corners":
            self.discard_corners()
            return
        if button == "Close fence":
            self.close_fence()
            return
        form = self._form(event, button)
        if form is not None:
            self.close_zone(form.get(ZONE_NAME) or "")

    def _corner_pressed(self, event: viser.GuiEvent) -> None:
        button = event.target.value
        if button == "Delete fence":
            self.delete_fence()
            return
        form = self._form(event, button)
        if form is None:
            return
        if button == "Move corner":
            got = self._numbers(form, ZONE_NO, CORNER_NO, CORNER_N, CORNER_E)
            if got is not None:
                self.move_corner(int(got[0]), int(got[1]), got[2], got[3])
        elif button == "Delete corner":
            got = self._numbers(form, ZONE_NO, CORNER_NO)
            if got is not None:
                self.delete_corner(int(got[0]), int(got[1]))
        else:
            got = self._numbers(form, ZONE_NO)
            if got is not None:
                self.delete_zone(int(got[0]))

    def _band_pressed(self, event: viser.GuiEvent) -> None:
        form = self._form(event, SET_BAND)
        if form is None:
            return
        try:
            floor = _optional_alt("Fence floor", form.get(FLOOR))
            ceiling = _optional_alt("Fence ceiling", form.get(CEILING))
        except InputError as exc:
            self._say(str(exc), error=True)
            return
        self.set_fence_band(floor, ceiling)

    def _rally_pressed(self, event: viser.GuiEvent) -> None:
        button = event.target.value
        form = self._form(event, button)
        if form is None:
            return
        if button == DELETE_RALLY:
            got = self._numbers(form, RALLY_NO)
            if got is not None:
                self.delete_rally(int(got[0]))
            return
        try:
            alt = _optional_alt("Point altitude", form.get(POINT_ALT))
        except InputError as exc:
            self._say(str(exc), error=True)
            return
        if button == MOVE_RALLY:
            got = self._numbers(form, RALLY_NO, CORNER_N, CORNER_E)
            if got is not None:
                self.move_rally(int(got[0]), got[1], got[2], alt)
            return
        got = self._numbers(form, CORNER_N, CORNER_E)
        if got is None:
            return
        if button == SET_HOME:
            self.set_home(got[0], got[1], alt)
        else:
            self.add_rally(got[0], got[1], alt, form.get(RALLY_NAME) or "")

    def _push_pressed(self, _event: viser.GuiEvent) -> None:
        self.push(self._operator())

    def _click_mode(self, mode: str) -> None:
        scene = self.client.scene
        if self._click is not None:
            scene.remove_click_callback(self._click)
            self._click = None
        if mode == CLICK_OFF:
            return

        @scene.on_click()
        def clicked(event: viser.SceneClickEvent) -> None:
            hit = ground_hit_ned(event.ray_origin, event.ray_direction)
            mode = self.ground.value
            if hit is None:
                self._say("that click does not hit the ground; aim below the horizon", error=True)
            elif mode == CLICK_ADD:
                self.add_corner(*hit)
            else:
                self._point_clicked(mode, *hit)

        self._click = clicked

    def _point_clicked(self, mode: str, n_m: float, e_m: float) -> None:
        """A ground click that moves a corner, sets home or adds or moves a rally point. A click
        is no button: the corner or rally point is the one the tab's fields name, the altitude
        the one its field holds, and the draft drawn in the view shows what changed before
        anything is pushed."""
        if mode == CLICK_MOVE:
            zone_no, corner_no = self.zone_no.value, self.corner_no.value
            if not all(isinstance(v, int | float) and v == int(v) for v in (zone_no, corner_no)):
                self._say("set a whole zone and corner number to move", error=True)
                return
            self.move_corner(int(zone_no), int(corner_no), n_m, e_m)
            return
        try:
            alt = _optional_alt("Point altitude", self.point_alt.value)
        except InputError as exc:
            self._say(str(exc), error=True)
            return
        if mode == CLICK_HOME:
            self.set_home(n_m, e_m, alt)
        elif mode == CLICK_RALLY:
            self.add_rally(n_m, e_m, alt, self.rally_name.value)
        else:
            rally_no = self.rally_no.value
            if not (isinstance(rally_no, int | float) and rally_no == int(rally_no)):
                self._say("set a whole rally point number to move", error=True)
                return
            self.move_rally(int(rally_no), n_m, e_m, alt)

    # -- showing -------------------------------------------------------------------------------
    def _say(self, text: str, error: bool = False) -> None:
        colour = "#b00020" if error else "#1b5e20"
        kind = "error" if error else "info"
        self.message.content = (
            f'<div data-plan-edit="{kind}" style="color:{colour}">{html.escape(text)}</div>'
        )

    def _show(self, draft: pe.Draft | None) -> None:
        """The draft in the folder and in this tab's view (lock held)."""
        self.draft_html.content = draft_html(draft)
        for handle in reversed(self._drawn):
            handle.remove()
        self._drawn = [] if draft is None else draw_draft(self.client.scene, draft)
