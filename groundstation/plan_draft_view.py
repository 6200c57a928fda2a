"""How a fleet plan draft is shown in one browser tab: the summary in the 'Edit fleet plan'
folder (`draft_html`) and the drawing in the tab's own 3D view (`draw_draft`), both numbering the
fence's and the zones' corners (zone.corner, the fence zone 0), home and the rally points
('rally k', comms/plan.py `rally_numbers`) as the steps take them (groundstation/plan_edit.py).

groundstation/plan_editor.py is the panel that calls them.
"""

from __future__ import annotations

import html

import numpy as np
import viser

from comms.plan import HOME, RallyPoint, rally_numbers
from groundstation import plan_edit as pe
from groundstation.scene import add_rally_point, polygon_segments

DRAFT_PATH = "/plan_draft"
DRAFT_RGB = (140, 60, 200)
MAX_CORNER_LABELS = 200
"""Corners numbered in the view at most (each is a label; home and the rally points, at most
comms/plan.py MAX_RALLY_POINTS, are labelled besides)."""


def draw_draft(scene: viser.SceneApi, draft: pe.Draft) -> list:
    """Draw `draft` in violet under DRAFT_PATH of this tab's scene: each polygon with its
    numbered corners, home and the numbered rally points, the corners being drawn; the handles
    made, parents before their children (remove them in reverse)."""
    drawn: list = []
    add = drawn.append
    colour = np.array(DRAFT_RGB, np.uint8)
    labels = 0
    for no, vertices_ne_m in _numbered_polygons(draft):
        add(
            scene.add_line_segments(
                f"{DRAFT_PATH}/polygons/{no}",
                polygon_segments(vertices_ne_m, 0.08),
                colour,
                thickness=3.0,
                thickness_units="screen",
            )
        )
        for j, (n, e) in enumerate(vertices_ne_m):
            if labels < MAX_CORNER_LABELS:
                labels += 1
                add(
                    scene.add_label(
                        f"{DRAFT_PATH}/corners/{no}_{j + 1}",
                        f"{no}.{j + 1}",
                        position=(e, n, 0.3),
                        font_screen_scale=0.8,
                    )
                )
    for no, r in _numbered_rally(draft):
        path = f"{DRAFT_PATH}/rally/{no or HOME}"
        add_rally_point(scene, path, r, _rally_name(no, r), DRAFT_RGB, add, 0.8)
    if draft.corners_ne_m:
        ne = np.asarray(draft.corners_ne_m, np.float32)
        pts = np.stack([ne[:, 1], ne[:, 0], np.full(len(ne), 0.08, np.float32)], axis=-1)
        add(
            scene.add_point_cloud(
                f"{DRAFT_PATH}/new/corners", pts, colour, point_size=0.6, point_shape="circle"
            )
        )
        if len(pts) >= 2:
            add(
                scene.add_line_segments(
                    f"{DRAFT_PATH}/new/edges",
                    np.stack([pts[:-1], pts[1:]], axis=1),
                    colour,
                    thickness=2.0,
                    thickness_units="screen",
                )
            )
    return drawn


def _numbered_polygons(draft: pe.Draft) -> list[tuple[int, tuple[tuple[float, float], ...]]]:
    """(number, corners) of the fence (pe.FENCE_NO) and of each zone (1 on), as steps take them."""
    g = draft.geometry
    fence = [] if g.fence is None else [(pe.FENCE_NO, g.fence.vertices_ne_m)]
    return fence + [(i + 1, z.vertices_ne_m) for i, z in enumerate(g.keep_out)]


def _numbered_rally(draft: pe.Draft) -> list[tuple[int, RallyPoint]]:
    """(number, point) of home (0) and of each rally point (1 on, comms/plan.py
    `rally_numbers`), as steps take them."""
    rally = draft.geometry.rally
    home = [(0, r) for r in rally if r.name == HOME]
    return home + [(no, rally[i]) for no, i in rally_numbers(rally)]


def _rally_name(no: int, r: RallyPoint) -> str:
    """'home', 'rally 2' or 'rally 2: pad': how the view labels a point."""
    if no == 0:
        return HOME
    return f"rally {no}" + (f": {r.name}" if r.name else "")


def _corners(no: int, vertices_ne_m: tuple[tuple[float, float], ...]) -> str:
    """'4 corners (1.1 to 1.4)': how many, and their numbers as the view labels them."""
    return f"{len(vertices_ne_m)} corners ({no}.1 to {no}.{len(vertices_ne_m)})"


def draft_html(draft: pe.Draft | None) -> str:
    """What the folder says of the draft: its base, the fence and each zone with its corners'
    numbers as the view labels them, home and the rally points numbered as the view labels
    them, the corners being drawn."""
    if draft is None:
        return "<i>not editing: a ground click or a button below starts a draft of the plan</i>"
    g = draft.geometry
    fence = "no fence"
    if g.fence is not None:
        f = g.fence
        band = [
            f"{w} {v:g} m"
            for w, v in (("floor", f.floor_alt_m), ("ceiling", f.ceiling_alt_m))
            if v is not None
        ]
        fence = f"zone {pe.FENCE_NO}: the fence, {_corners(pe.FENCE_NO, f.vertices_ne_m)}" + (
            f" ({', '.join(band)})" if band else ""
        )
    zones = "".join(
        f"<br>zone {i + 1}: {html.escape(z.name or 'unnamed')}, {_corners(i + 1, z.vertices_ne_m)}"
        for i, z in enumerate(g.keep_out)
    )
    points = "".join(
        f"<br>{html.escape(_rally_name(no, r))} at {pe.where(r)}"
        for no, r in _numbered_rally(draft)
    )
    if not any(r.name == HOME for r in g.rally):
        points = "<br>no home" + points
    base = f"v{draft.base_version}" if draft.base_version is not None else "no plan"
    head = f"<b>draft</b> on {base}, {len(draft.edits)} edit(s) not pushed"
    drawing = (
        f"<br>drawing a zone or fence: {len(draft.corners_ne_m)} corner(s)"
        if draft.corners_ne_m
        else ""
    )
    body = f"{head}<br>{fence}{zones}{points}{drawing}"
    return f"<div data-draft='{len(draft.edits)}'>{body}</div>"
