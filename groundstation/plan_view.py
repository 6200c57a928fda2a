"""The fleet plan in the browser station: followed on the mesh, drawn on the ground, listed in
the panel, and replaced from a file an operator uploads (GeoJSON or QGC .plan) or from the edits
an operator makes in the browser (groundstation/plan_editor.py), signed with this station's key
and pushed to the fleet (`push_geometry`, the one push path), each version listed in the command
log with who pushed it. The vehicles' routes around the zones are drawn too (plan_routes.py).

The station is a plan member like any vehicle (comms/plan_sync.py): it answers a rebooted
vehicle's pull with the plan it holds. What arrives on a Zenoh thread is only noted; the render
thread draws it (`tick`), as the rest of the scene.
"""

from __future__ import annotations

import html
import threading
import time
from typing import Any

import viser

from comms.doc_sync import Offer
from comms.geo import GeoOrigin
from comms.plan import FleetPlan, PadLayout
from comms.plan_io import BadPlanError, PlanGeometry, next_version, parse_plan
from comms.plan_sync import PlanSync, describe
from groundstation.command_log import CommandLog
from groundstation.plan_edit import EditRefused, check_landing
from groundstation.plan_routes import RouteLayer
from groundstation.scene import FleetScene
from groundstation.web_viser import operator_of


class PlanView:
    """The station's plan follower, its list in the panel and its upload button."""

    def __init__(
        self,
        server: viser.ViserServer,
        mesh: Any,
        scene: FleetScene,
        origin: GeoOrigin,
        *,
        order: float,
        log: CommandLog | None = None,
        states=None,
        separation_m: float = 3.0,
        pads: PadLayout = PadLayout(),
        route_period_s: float = 0.5,
        clock_ns=time.time_ns,
    ) -> None:
        """`mesh`: the station's comms.mesh.Mesh (its auth signs pushed plans). `log`: where
        each plan version is listed. `states()`: the vehicles' latest VehicleStates, whose
        routes are drawn every `route_period_s` (None: no routes)."""
        self.server, self.mesh, self.scene, self.origin = server, mesh, scene, origin
        self.log, self._states = log, states
        self._clock_ns = clock_ns
        self.separation_m = separation_m
        """The fleet's separation: routes are drawn and home and rally points checked at it."""
        self.pads = pads
        """The landing pads around home and each rally point, checked with them."""
        self.routes = RouteLayer(server, separation_m)
        self._route_period_ns = int(route_period_s * 1e9)
        self._routes_ns = 0
        self._lock = threading.Lock()
        self._pending: tuple[FleetPlan | None] | None = None
        self.drawn: FleetPlan | None = None
        """The plan on screen (read by tests)."""
        gui = server.gui
        with gui.add_folder("Fleet plan", order=order):
            self.html = gui.add_html(plan_html(None))
            self.status = gui.add_html("")
            self.upload = gui.add_upload_button(
                "Load plan file (GeoJSON or QGC .plan), sign, push",
                hint="checked, signed with this station's key and sent to every vehicle",
                mime_type="*/*",
            )
        self.upload.on_upload(self._on_upload)
        self.sync = PlanSync(mesh.session, mesh.fleet, mesh.auth, on_plan=self._on_plan)

    def close(self) -> None:
        self.sync.undeclare()

    def _on_plan(self, plan: FleetPlan) -> None:
        if self.log is not None:
            self.log.on_plan(plan.version, plan.signer_id, describe(plan), self._clock_ns())
        with self._lock:
            self._pending = (plan,)

    def tick(self) -> None:
        """Draw a plan that arrived since the last tick (the render thread)."""
        with self._lock:
            pending, self._pending = self._pending, None
        now_ns = self._clock_ns()
        if pending is not None:
            (plan,) = pending
            self.routes.set_plan(plan)
            with self.server.atomic():
                self.scene.update_plan(plan)
            self.html.content = plan_html(plan)
            self.drawn = plan
        elif self._states is None or now_ns - self._routes_ns < self._route_period_ns:
            return
        self._routes_ns = now_ns
        if self._states is not None:
            with self.server.atomic():
                self.routes.draw(self._states())

    def load(self, raw: bytes, name: str, operator: str | None = None) -> str:
        """Check an uploaded file (as `covey plan load` does: comms/plan_io.py, then home and the
        rally points' zone clearance, plan_edit.py `check_landing`), sign it as this station,
        push it; the line to show."""
        where = f"uploaded {name!r}"
        try:
            geometry = parse_plan(raw, where, self.origin)
            check_landing(geometry, self.separation_m, pads=self.pads)
        except BadPlanError as exc:
            return f"refused: {exc}"
        except EditRefused as exc:
            return f"refused: {where}: {exc}"
        return self.push_geometry(geometry, f"from {name!r}", operator)

    def push_geometry(self, geometry: PlanGeometry, what: str, operator: str | None) -> str:
        """Make `geometry` (checked) the fleet's next plan version, signed as this station,
        applied here and put on the mesh, listed in the command log as `what` (the file, the
        edits) by `operator`; the line to show."""
        now_ns = self._clock_ns()
        plan = geometry.plan(self.mesh.fleet, next_version(self.sync.plan, now_ns), now_ns)
        auth = self.mesh.auth
        if auth is not None:
            plan = auth.sign_plan(plan)
        if self.log is not None:
            self.log.mark_own_plan(plan.version, operator or "", what)
        result = self.sync.push(plan)
        if result is not Offer.APPLIED:
            return f"refused: plan v{plan.version} was not applied here ({result.value})"
        who = f" by {operator}" if operator else ""
        notes = "".join(f"; {n}" for n in geometry.notes)
        return f"plan v{plan.version} {what} pushed{who}{notes}"

    def _on_upload(self, event: viser.GuiEvent) -> None:
        upload = self.upload.value
        operator = operator_of(self.server, event.client_id) if event.client_id else None
        line = self.load(upload.content, upload.name, operator)
        error = line.startswith("refused")
        colour = "#b00020" if error else "#1b5e20"
        self.status.content = f'<div style="color:{colour}">{html.escape(line)}</div>'


def plan_html(plan: FleetPlan | None) -> str:
    """The plan as a short list: fence, zones, rally points."""
    if plan is None:
        return "<i>no fleet plan: the vehicles' circular geofence applies</i>"
    rows = []
    who = "fleet authority" if plan.signer_id == 0 else f"station {plan.signer_id}"
    rows.append(f"<b>v{plan.version}</b>, signed by {who}")
    if plan.fence is not None:
        f = plan.fence
        band = ", ".join(
            f"{a} {v:g} m"
            for a, v in (("floor", f.floor_alt_m), ("ceiling", f.ceiling_alt_m))
            if v is not None
        )
        rows.append(f"fence: {len(f.vertices_ne_m)} vertices" + (f" ({band})" if band else ""))
    for z in plan.keep_out:
        top = "" if z.ceiling_alt_m is None else f", up to {z.ceiling_alt_m:g} m"
        rows.append(f"keep out: {html.escape(z.name or 'unnamed')}{top}")
    for r in plan.rally:
        rows.append(f"{html.escape(r.name or 'rally')}: N {r.n_m:.0f} m, E {r.e_m:.0f} m")
    return "<br>".join(rows)
