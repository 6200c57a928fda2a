"""The station's mission section: one tab of the command panel (groundstation/panel.py).

The operator loads a mission file (covey JSON or a QGC `.plan`, through the upload button,
checked by groundstation/mission_io.py) or clicks waypoints on the ground (each at the
waypoint altitude the form shows when 'Upload mission' is pressed), sees the route in this tab's
3D view, and uploads it to the Targets: one query, one ack per vehicle in the tab's ack matrix,
as every command. Start, pause, resume and abort are commands like land or hold, with the same
per-tab form guard; the vehicles that accepted an upload show their route in the shared scene
(groundstation/scene.py) and their progress (item k/n) in the fleet table.
"""

from __future__ import annotations

from collections.abc import Callable

import viser

from comms.geo import GeoOrigin
from comms.schema import MAX_MISSION_ITEMS, CommandKind, MissionItem, MissionItemKind
from groundstation.browser_form import FormSnapshot
from groundstation.frames import ground_hit_ned
from groundstation.inputs import CommandRequest, InputError, number, simple
from groundstation.mission_io import (
    MAX_MISSION_FILE_BYTES,
    MissionFileError,
    MissionRequest,
    mission_from_text,
)
from groundstation.scene import route_segments
from kit.safe_load import BadFileError, decode_utf8

WP_ALT = "Waypoint altitude above origin (m)"
LABELS = (WP_ALT,)
"""The labelled inputs a clicked route is built from (read from the tab at each click)."""
CONTROL_BUTTONS = {
    "Start": CommandKind.MISSION_START,
    "Pause": CommandKind.MISSION_PAUSE,
    "Resume": CommandKind.MISSION_RESUME,
    "Abort": CommandKind.MISSION_ABORT,
}
PREVIEW_PATH = "/mission/preview"
ROUTE_RGB = (0, 150, 140)
"""The MISSION mode's colour (groundstation/palette.py)."""

Job = tuple[CommandRequest | MissionRequest, tuple[int, ...]]


class MissionSection:
    """The mission tab of one browser tab's panel."""

    def __init__(
        self,
        client: viser.ClientHandle,
        *,
        read_form: Callable[[viser.GuiEvent, str], FormSnapshot],
        targets: Callable[[FormSnapshot], tuple[int, ...]],
        send: Callable[[str, list[Job]], None],
        say: Callable[..., None],
        origin: GeoOrigin,
        goto_limit_m: float,
    ) -> None:
        self.client = client
        self._read_form, self._targets, self._send, self._say = read_form, targets, send, say
        self._origin, self._limit_m = origin, goto_limit_m
        self.loaded: MissionRequest | None = None
        """The last file loaded in this tab."""
        self.clicked_ne_m: list[tuple[float, float]] = []
        """Waypoints clicked on the ground in this tab (they win over a loaded file)."""
        self._click: Callable | None = None
        gui = client.gui
        self.upload = gui.add_upload_button(
            "Load mission file",
            icon=viser.Icon.UPLOAD,
            hint="covey mission JSON or a QGroundControl .plan (waypoint, loiter time, take-off, "
            "land, return)",
        )
        self.pick = gui.add_checkbox("Click ground to add waypoints", False)
        self.wp_alt = gui.add_number(
            WP_ALT, 8.0, step=0.5, hint="Metres, up, above the fleet origin, for clicked waypoints."
        )
        self.clear_button = gui.add_button("Clear route", icon=viser.Icon.TRASH)
        self.send_button = gui.add_button("Upload mission", icon=viser.Icon.SEND)
        self.control = gui.add_button_group("Mission", tuple(CONTROL_BUTTONS))
        self.upload.on_upload(lambda e: self.load(e.target.value.name, e.target.value.content))
        self.pick.on_update(lambda _e: self._pick_mode(self.pick.value))
        self.clear_button.on_click(lambda _e: self.clear())
        self.send_button.on_click(self.send)
        self.control.on_click(self.command)

    # -- building the route ----------------------------------------------------------------
    def load(self, name: str, content: bytes) -> None:
        """A file came from the tab's upload button: check it, keep it, draw it."""
        what = f"mission file {name}"
        try:
            if len(content) > MAX_MISSION_FILE_BYTES:
                raise MissionFileError(f"{what} is over the {MAX_MISSION_FILE_BYTES} byte limit")
            loaded = mission_from_text(decode_utf8(content, what), what)
        except BadFileError as exc:
            self._say(str(exc), error=True)
            return
        self.loaded = MissionRequest(loaded.items, loaded.mission_id)
        self.clicked_ne_m = []
        self._draw(self.loaded.route_ned_m(self._origin))
        self._say(
            f"Loaded {name}: mission {loaded.mission_id}, {len(loaded.items)} items, drawn in "
            "the view; press 'Upload mission' to send it to the Targets."
        )

    def add_waypoint(self, n_m: float, e_m: float) -> None:
        if len(self.clicked_ne_m) >= MAX_MISSION_ITEMS:
            self._say(f"A mission holds at most {MAX_MISSION_ITEMS} items.", error=True)
            return
        if abs(n_m) > self._limit_m or abs(e_m) > self._limit_m:
            self._say(
                f"Waypoint N {n_m:.1f} E {e_m:.1f} is beyond {self._limit_m:g} m.", error=True
            )
            return
        self.clicked_ne_m.append((round(n_m, 1), round(e_m, 1)))
        alt = float(self.wp_alt.value or 0.0)
        self._draw([(n, e, -alt) for n, e in self.clicked_ne_m])
        self._say(
            f"Waypoint {len(self.clicked_ne_m)} at N {n_m:.1f} E {e_m:.1f}; press 'Upload "
            "mission' to send the clicked route."
        )

    def clear(self) -> None:
        self.loaded, self.clicked_ne_m = None, []
        self._draw([])

    def _draw(self, points_ned_m) -> None:
        segments = route_segments(points_ned_m)
        self.client.scene.add_line_segments(
            PREVIEW_PATH,
            points=segments,
            colors=ROUTE_RGB,
            thickness=3.0,
            thickness_units="screen",
            visible=len(segments) > 0,
        )

    def _pick_mode(self, on: bool) -> None:
        scene = self.client.scene
        if self._click is not None:
            scene.remove_click_callback(self._click)
            self._click = None
        if not on:
            return

        @scene.on_click()
        def clicked(event: viser.SceneClickEvent) -> None:
            hit = ground_hit_ned(event.ray_origin, event.ray_direction)
            if hit is None:
                self._say("That click does not hit the ground; aim below the horizon.", error=True)
                return
            self.add_waypoint(*hit)

        self._click = clicked

    # -- sending -----------------------------------------------------------------------------
    def request(self, form: FormSnapshot) -> MissionRequest:
        """The mission to upload: the clicked route at the form's waypoint altitude, else the
        loaded file. InputError says why there is none."""
        if self.clicked_ne_m:
            alt = number("Waypoint altitude above origin", form.get(WP_ALT), 0.5, 10_000.0, " m")
            items = tuple(
                MissionItem(MissionItemKind.WAYPOINT, x=n, y=e, alt_m=alt)
                for n, e in self.clicked_ne_m
            )
            return MissionRequest(items)
        if self.loaded is None:
            raise InputError("Mission: load a file or click waypoints on the ground first")
        return self.loaded

    def send(self, event: viser.GuiEvent) -> None:
        try:
            form = self._read_form(event, "Upload mission")
            req = self.request(form)
            targets = self._targets(form)
        except InputError as exc:
            self._say(str(exc), error=True)
            return
        who = "all vehicles" if not targets else "vehicle(s) " + ",".join(map(str, targets))
        self._say(f"Uploading {req.describe()} to {who} …")
        self._send(f"{req.describe()} → {who}", [(req, targets)])

    def command(self, event: viser.GuiEvent) -> None:
        kind = CONTROL_BUTTONS[event.target.value]
        try:
            form = self._read_form(event, event.target.value)
            targets = self._targets(form)
        except InputError as exc:
            self._say(str(exc), error=True)
            return
        req = simple(kind)
        who = "all vehicles" if not targets else "vehicle(s) " + ",".join(map(str, targets))
        self._send(f"{req.describe()} → {who}", [(req, targets)])
