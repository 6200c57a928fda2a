"""The station's formation section: one tab of the command panel (groundstation/panel.py).

The operator sets spacing, centre, altitude and heading, and presses a shape: the station
computes the slots and the optimal assignment (groundstation/formation.py) from the vehicles'
latest positions, checks every slot as its vehicle would (a slot it would refuse, nearer a
keep-out zone than its filter keeps at its reported position sigma, refuses the whole formation
with the reason; a slot it would move is shown and sent moved) and draws it in this tab's 3D view, one line from each vehicle to its slot.
"Send formation" then sends exactly that previewed assignment (one goto per vehicle, acked in
the tab's ack matrix like any command), and only if the form still shows what was previewed:
a changed field or Targets refuses with the reason, and nothing is sent. A formation sent
before keeps each vehicle's slot when moved (the station's FormationMemory, shared by tabs).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import viser

from comms.plan import FleetPlan
from groundstation.browser_form import FormSnapshot
from groundstation.formation import (
    FormationError,
    FormationMemory,
    FormationPlan,
    FormationSpec,
)
from groundstation.formation import plan_formation as plan
from groundstation.frames import ned_to_scene
from groundstation.inputs import CommandRequest, InputError, goto_local, number

SPACING, CENTRE_N, CENTRE_E = "Spacing (m)", "Centre north (m)", "Centre east (m)"
FORM_ALT, HEADING = "Formation altitude above origin (m)", "Heading (deg)"
LABELS = (SPACING, CENTRE_N, CENTRE_E, FORM_ALT, HEADING)
"""The labelled inputs a formation is built from (read from the tab at each click)."""
SHAPE_BUTTONS = {"Grid": "grid", "Line": "line", "Circle": "circle", "V": "v"}
SCENE_PATH = "/formation/assignment"
LINE_RGB = (40, 160, 80)


@dataclass(frozen=True)
class Preview:
    """What the tab showed and drew when a shape was pressed."""

    form: tuple[tuple[str, str], ...]
    """The labelled inputs (and Targets) at the click: Send requires the same."""
    spec: FormationSpec
    plan: FormationPlan
    jobs: tuple[tuple[CommandRequest, tuple[int, ...]], ...]
    """One goto per vehicle to its slot, as it will be sent."""


class FormationSection:
    """The formation tab of one browser tab's panel."""

    def __init__(
        self,
        client: viser.ClientHandle,
        *,
        read_form: Callable[[viser.GuiEvent, str], FormSnapshot],
        targets: Callable[[FormSnapshot], tuple[int, ...]],
        positions: Callable[[], Mapping[int, tuple[float, float, float]]],
        pos_sigmas: Callable[[], Mapping[int, float]] = dict,
        memory: FormationMemory,
        separation_m: float,
        plan_of_fleet: Callable[[], FleetPlan | None],
        send: Callable[[str, list[tuple[CommandRequest, tuple[int, ...]]]], None],
        say: Callable[..., None],
        goto_limit_m: float,
        targets_label: str,
    ) -> None:
        self.client = client
        self._read_form, self._targets, self._positions = read_form, targets, positions
        self._pos_sigmas = pos_sigmas
        self._memory, self._separation_m, self._plan_of_fleet = memory, separation_m, plan_of_fleet
        self._send, self._say = send, say
        self._goto_limit_m, self._targets_label = goto_limit_m, targets_label
        self.preview: Preview | None = None
        gui = client.gui
        self.spacing = gui.add_number(SPACING, 6.0, step=0.5, hint="Between neighbouring slots.")
        self.centre_n = gui.add_number(CENTRE_N, 0.0, step=1.0, hint="Metres north of the origin.")
        self.centre_e = gui.add_number(CENTRE_E, 0.0, step=1.0, hint="Metres east of the origin.")
        self.alt = gui.add_number(FORM_ALT, 8.0, step=0.5, hint="Metres, up, above the origin.")
        self.heading = gui.add_number(HEADING, 0.0, step=5.0, hint="Clockwise from north.")
        self.shapes = gui.add_button_group("Preview", tuple(SHAPE_BUTTONS))
        self.send_button = gui.add_button("Send formation", icon=viser.Icon.SEND)
        self.shapes.on_click(lambda e: self.show(e, SHAPE_BUTTONS[e.target.value]))
        self.send_button.on_click(self.send)

    def _shown(self, form: FormSnapshot) -> tuple[tuple[str, str], ...]:
        return tuple((k, form.get(k)) for k in (self._targets_label, *LABELS))

    def show(self, event: viser.GuiEvent, shape: str) -> None:
        """A shape was pressed: plan it from the form and draw the assignment."""
        try:
            form = self._read_form(event, shape.capitalize())
            spec = FormationSpec(
                shape,
                number("Spacing", form.get(SPACING), 0.0, 10_000.0, " m"),
                (
                    number(
                        "Centre north",
                        form.get(CENTRE_N),
                        -self._goto_limit_m,
                        self._goto_limit_m,
                        " m",
                    ),
                    number(
                        "Centre east",
                        form.get(CENTRE_E),
                        -self._goto_limit_m,
                        self._goto_limit_m,
                        " m",
                    ),
                ),
                number("Formation altitude", form.get(FORM_ALT), 0.0, 10_000.0, " m"),
                number("Heading", form.get(HEADING), -360.0, 360.0, "°"),
            )
            targets = self._targets(form)
            known = self._positions()
            ids = targets or tuple(sorted(known))
            positions = {vid: known.get(vid) for vid in ids}
            # a preview recalls a moved formation's slots but remembers nothing until it is sent
            fp = plan(
                spec,
                positions,
                self._separation_m,
                plan=self._plan_of_fleet(),
                memory=FormationMemory.from_json(self._memory.to_json()),
                pos_sigma_m=self._pos_sigmas(),
            )
            jobs = [  # each goto checked as the operator's own would be
                (goto_local(t[0], t[1], -t[2], self._goto_limit_m), (vid,))
                for vid, t in zip(fp.vehicle_ids, fp.targets_ned_m.tolist(), strict=True)
            ]
        except (InputError, FormationError) as exc:
            self.clear()
            self._say(f"Formation: {exc}", error=True)
            return
        self.preview = Preview(self._shown(form), spec, fp, tuple(jobs))
        segments = np.stack([fp.from_ned_m, fp.targets_ned_m], axis=1)
        self.client.scene.add_line_segments(
            SCENE_PATH,
            points=ned_to_scene(segments).astype(np.float32),
            colors=LINE_RGB,
            thickness=3.0,
            thickness_units="screen",
        )
        how = "slots kept from when it was sent" if fp.kept else "optimal assignment"
        far = max(np.linalg.norm(fp.targets_ned_m - fp.from_ned_m, axis=1))
        moved = "".join(
            f" Vehicle {vid}'s slot: {why}."
            for vid, why in zip(
                fp.vehicle_ids, fp.moved or ("",) * len(fp.vehicle_ids), strict=True
            )
            if why
        )
        self._say(
            f"Formation {shape}, {len(fp.vehicle_ids)} vehicles ({how}, longest leg "
            f"{far:.0f} m) drawn in the view; press 'Send formation' to send it.{moved}"
        )

    def send(self, event: viser.GuiEvent) -> None:
        """Send the previewed formation, if the form still shows what was previewed."""
        preview = self.preview
        if preview is None:
            self._say("Formation: press a shape first to see the assignment.", error=True)
            return
        try:
            form = self._read_form(event, "Send formation")
        except InputError as exc:
            self._say(f"Formation not sent: {exc}", error=True)
            return
        if self._shown(form) != preview.form:
            self._say(
                "Formation not sent: the form changed since the preview; press the shape again.",
                error=True,
            )
            return
        fp = preview.plan
        self._memory.remember(
            preview.spec.key(fp.vehicle_ids), dict(zip(fp.vehicle_ids, fp.slot_of, strict=True))
        )
        jobs = list(preview.jobs)
        self.preview = None
        self._send(f"formation {preview.spec.shape} ({len(jobs)} vehicles)", jobs)

    def clear(self) -> None:
        self.preview = None
        self.client.scene.add_line_segments(
            SCENE_PATH, points=np.zeros((0, 2, 3), np.float32), colors=LINE_RGB, visible=False
        )
