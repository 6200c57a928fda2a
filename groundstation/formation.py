"""Formations: the slots of a shape, which vehicle takes which slot, and why a formation is
refused. Pure: no mesh, no clock; `covey cmd formation` and the station's formation section
both call `plan_formation`, then send one goto per vehicle through the ordinary command path.

Slots are computed in the formation's own frame, forward (along the heading) and right, with
the shape's centroid at the origin, then turned by the heading and moved to the centre:

    N = N_c + f cos h - r sin h        E = E_c + f sin h + r cos h

Which vehicle takes which slot is the assignment of minimum total squared distance
(`scipy.optimize.linear_sum_assignment`). Squared distances make the straight paths of an
optimal assignment cross nowhere: two crossing paths a->y, b->x can always be uncrossed into a
cheaper pair. Moving a formation (a new centre, heading or altitude) keeps each vehicle's slot:
the assignment is remembered per formation (`FormationMemory`: shape, spacing, slot file and
the vehicles) and the slots move rigidly, so the fleet translates and turns as one body.
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from comms.plan import FleetPlan, plan_refusal
from comms.schema import LOCAL_DOWN_RANGE_M
from kit.safe_load import decode_utf8, parse_json, read_bounded

SHAPES = ("grid", "line", "circle", "v", "file")
"""The shapes `covey cmd formation` and the station offer ("file": slots from a JSON file)."""
MAX_SLOTS = 1024
"""Most slots one formation may have (a slot file is refused past it)."""
MAX_SLOT_FILE_BYTES = 256 * 1024
"""Largest slot file read."""
V_WING_DEG = 45.0
"""Angle of each wing of a V to the heading's reverse (the slots along a wing are `spacing`
apart, the two wings' k-th slots 2 k spacing sin 45° apart)."""
MAX_REMEMBERED = 32
"""How many formations a FormationMemory keeps (the oldest is forgotten first)."""


class FormationError(ValueError):
    """A formation that cannot be flown; str() says why, to show as is. Nothing is sent."""


@dataclass(frozen=True)
class FormationSpec:
    """A formation as the operator asks for it."""

    shape: str
    """One of SHAPES."""
    spacing_m: float
    """Distance between neighbouring slots (a grid's rows and columns, a circle's chord, a
    line's gap, a V's step along a wing); a file's slots are used as given."""
    center_ne_m: tuple[float, float]
    """The shape's centroid, north and east of the fleet origin, metres."""
    alt_m: float
    """Altitude of every slot above the fleet origin, up, metres."""
    heading_deg: float = 0.0
    """Direction the formation faces, degrees clockwise from north (a line stands across it,
    a V points along it)."""
    file_slots_fr_m: tuple[tuple[float, float], ...] = ()
    """For shape "file": each slot's (forward, right) metres from the centre (at heading 0:
    north, east)."""

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise FormationError(f"shape {self.shape!r}: choose one of {', '.join(SHAPES)}")
        for name, v in (
            ("--spacing-m", self.spacing_m),
            ("--alt-m", self.alt_m),
            ("--heading-deg", self.heading_deg),
            ("--center-ne-m", self.center_ne_m[0]),
            ("--center-ne-m", self.center_ne_m[1]),
        ):
            if not math.isfinite(v):
                raise FormationError(f"{name}: must be a finite number, got {v}")
        if self.shape != "file" and self.spacing_m <= 0:
            raise FormationError(f"--spacing-m: must be positive, got {self.spacing_m:g}")
        lo, hi = -LOCAL_DOWN_RANGE_M[1], -LOCAL_DOWN_RANGE_M[0]
        if not (self.alt_m > 0 and lo <= self.alt_m <= hi):
            raise FormationError(
                f"--alt-m: {self.alt_m:g} m must be above the origin, within (0, {hi:g}] m"
            )
        if self.shape == "file" and not self.file_slots_fr_m:
            raise FormationError("shape 'file' needs --slots FILE")
        if self.shape != "file" and self.file_slots_fr_m:
            raise FormationError(f"--slots is for shape 'file', not {self.shape!r}")

    def key(self, vehicle_ids: tuple[int, ...]) -> str:
        """What makes two requests the same formation (so that moving it keeps the slots): the
        shape, its spacing and file slots, and the vehicles; not the centre, heading or altitude."""
        return json.dumps(
            [self.shape, round(self.spacing_m, 6), self.file_slots_fr_m, sorted(vehicle_ids)]
        )


def shape_offsets_fr_m(shape: str, n: int, spacing_m: float) -> np.ndarray:
    """(n, 2) slot offsets (forward, right) of a generated shape, centroid at the origin."""
    k = np.arange(n, dtype=float)
    if n == 0:
        return np.zeros((0, 2))
    if shape == "line":  # abreast, across the heading
        fr = np.stack([np.zeros(n), k * spacing_m], axis=1)
    elif shape == "grid":
        side = math.ceil(math.sqrt(n))
        fr = np.stack([-(k // side) * spacing_m, (k % side) * spacing_m], axis=1)
    elif shape == "circle":
        # chord between neighbours = spacing: R = s / (2 sin(pi / n))
        radius_m = 0.0 if n == 1 else spacing_m / (2.0 * math.sin(math.pi / n))
        ang = 2.0 * math.pi * k / n
        fr = np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang)], axis=1)
    elif shape == "v":  # apex first, then the wings' slots alternately right and left
        step = np.ceil(k / 2.0)
        hand = np.where(k % 2 == 1, 1.0, -1.0)  # right, left, right, ...
        wing = math.radians(V_WING_DEG)
        fr = np.stack(
            [-step * spacing_m * math.cos(wing), hand * step * spacing_m * math.sin(wing)], axis=1
        )
    else:
        raise FormationError(f"shape {shape!r} has no generated slots")
    return fr - fr.mean(axis=0)


def place_ned_m(
    fr_m: np.ndarray, center_ne_m: tuple[float, float], heading_deg: float, alt_m: float
) -> np.ndarray:
    """(n, 3) NED slots: offsets (forward, right) turned by the heading and moved to the centre."""
    h = math.radians(heading_deg)
    c, s = math.cos(h), math.sin(h)
    f, r = fr_m[:, 0], fr_m[:, 1]
    n_m = center_ne_m[0] + f * c - r * s
    e_m = center_ne_m[1] + f * s + r * c
    return np.stack([n_m, e_m, np.full(len(fr_m), -alt_m)], axis=1)


def slots_ned_m(spec: FormationSpec, n: int) -> np.ndarray:
    """The spec's slots for n vehicles (a file's own slots, whatever n), NED."""
    if spec.shape == "file":
        fr = np.array(spec.file_slots_fr_m, dtype=float).reshape(-1, 2)
    else:
        fr = shape_offsets_fr_m(spec.shape, n, spec.spacing_m)
    return place_ned_m(fr, spec.center_ne_m, spec.heading_deg, spec.alt_m)


def assign(pos_ned_m: np.ndarray, slots_ned_m_: np.ndarray) -> np.ndarray:
    """slot[i] for vehicle row i: the assignment of minimum sum of squared 3-D distances
    (rows == slots; scipy's Jonker-Volgenant, O(n^3))."""
    from scipy.optimize import linear_sum_assignment  # not at import: `covey cmd` starts fast

    d = pos_ned_m[:, None, :] - slots_ned_m_[None, :, :]
    cost = np.einsum("ijk,ijk->ij", d, d)
    rows, cols = linear_sum_assignment(cost)
    out = np.empty(len(pos_ned_m), np.int64)
    out[rows] = cols
    return out


def closest_pair(points_ned_m: np.ndarray) -> tuple[int, int, float]:
    """(a, b, distance) of the two closest points (a < b); (-1, -1, inf) for fewer than two."""
    if len(points_ned_m) < 2:
        return -1, -1, math.inf
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points_ned_m).query(points_ned_m, k=2)  # column 1: nearest other
    a = int(np.argmin(dist[:, 1]))
    b = int(idx[a, 1])
    return min(a, b), max(a, b), float(dist[a, 1])


@dataclass(frozen=True)
class FormationPlan:
    """Which vehicle flies to which slot."""

    vehicle_ids: tuple[int, ...]
    """The vehicles, ascending."""
    slot_of: tuple[int, ...]
    """slot_of[i]: the slot index of vehicle_ids[i]."""
    targets_ned_m: np.ndarray
    """(n, 3) vehicle_ids[i]'s slot, NED."""
    from_ned_m: np.ndarray
    """(n, 3) where each vehicle was when the plan was made, NED."""
    kept: bool
    """The slots of a remembered formation were kept (it was moved), not assigned anew."""
    moved: tuple[str, ...] = ()
    """moved[i]: how vehicle_ids[i]'s slot was moved out of a zone's clearance, as its ack will
    say it ("" or (): not moved); `targets_ned_m` holds the moved slot."""

    def lines(self) -> list[str]:
        """The assignment as an operator reads it (altitude up, above the origin)."""
        out = []
        moved = self.moved or ("",) * len(self.vehicle_ids)
        for vid, slot, t, p, why in zip(
            self.vehicle_ids, self.slot_of, self.targets_ned_m, self.from_ned_m, moved, strict=True
        ):
            dist = float(np.linalg.norm(t - p))
            out.append(
                f"vehicle {vid:>5} -> slot {slot:>3}: N {t[0]:.1f} E {t[1]:.1f} "
                f"alt {-t[2]:.1f} m ({dist:.1f} m away)" + (f"; {why}" if why else "")
            )
        return out

    @property
    def cost_m2(self) -> float:
        """Sum of squared straight-line distances (what the assignment minimises)."""
        return float(((self.targets_ned_m - self.from_ned_m) ** 2).sum())


class FormationMemory:
    """The assignments of recent formations, by `FormationSpec.key`: a moved formation keeps
    them. Bounded (MAX_REMEMBERED, oldest forgotten); JSON for `covey cmd`'s state file."""

    def __init__(self, entries: Mapping[str, Mapping[int, int]] | None = None) -> None:
        self._entries: OrderedDict[str, dict[int, int]] = OrderedDict()
        for k, v in (entries or {}).items():
            self.remember(k, v)

    def recall(self, key: str) -> dict[int, int] | None:
        got = self._entries.get(key)
        return dict(got) if got is not None else None

    def remember(self, key: str, slot_by_vehicle: Mapping[int, int]) -> None:
        self._entries[key] = {int(v): int(s) for v, s in slot_by_vehicle.items()}
        self._entries.move_to_end(key)
        while len(self._entries) > MAX_REMEMBERED:
            self._entries.popitem(last=False)

    def forget(self, key: str) -> None:
        self._entries.pop(key, None)

    def to_json(self) -> str:
        return json.dumps({k: {str(v): s for v, s in e.items()} for k, e in self._entries.items()})

    @classmethod
    def from_json(cls, text: str) -> FormationMemory:
        """A memory from `to_json`'s text; anything malformed is ignored (a fresh memory)."""
        try:
            raw = json.loads(text)
            return cls({k: {int(v): int(s) for v, s in e.items()} for k, e in raw.items()})
        except (ValueError, TypeError, AttributeError):
            return cls()


def plan_formation(
    spec: FormationSpec,
    positions_ned_m: Mapping[int, tuple[float, float, float] | None],
    separation_m: float,
    *,
    plan: FleetPlan | None = None,
    memory: FormationMemory | None = None,
    reassign: bool = False,
    pos_sigma_m: Mapping[int, float] | None = None,
) -> FormationPlan:
    """Slots for the vehicles of `positions_ned_m` (id -> NED position, None: not heard yet),
    and which vehicle takes which. Raises FormationError with the reason for: no vehicles, a
    vehicle without a position, as many slots as vehicles not given (a slot file), two slots
    closer than `separation_m`, a slot refused by the fleet plan (fence, keep-out zone,
    ceiling or floor), a slot its vehicle would refuse (nearer a zone than its filter keeps, as
    `groundstation.target_check` finds at the vehicle's `pos_sigma_m`, id -> its reported
    position 1-sigma, 0 where missing; `separation_m` is the fleet's separation the filter
    keeps), and slots moved out of a zone's clearance that end nearer each other than the
    formation's spacing. With `memory`, a formation that was flown before keeps its assignment
    (unless `reassign`); the new assignment is remembered."""
    ids = tuple(sorted(positions_ned_m))
    if not ids:
        raise FormationError("no vehicles to put in formation")
    missing = [vid for vid in ids if positions_ned_m[vid] is None]
    if missing:
        raise FormationError(
            f"no position yet from vehicle {', '.join(map(str, missing))}: nothing sent"
        )
    slots = slots_ned_m(spec, len(ids))
    if len(slots) > len(ids):
        raise FormationError(
            f"{len(slots)} slots for {len(ids)} vehicles: more slots than vehicles "
            "(a formation fills every slot; give as many slots as vehicles)"
        )
    if len(slots) < len(ids):
        raise FormationError(
            f"{len(slots)} slots for {len(ids)} vehicles: more vehicles than slots"
        )
    a, b, d_m = closest_pair(slots)
    if d_m < separation_m - 1e-6:  # spacing == separation is allowed, to rounding
        raise FormationError(
            f"slots {a} and {b} are {d_m:.2f} m apart, closer than the {separation_m:g} m "
            "separation (widen --spacing-m)"
        )
    for k, (n_m, e_m, down_m) in enumerate(slots.tolist()):
        why = plan_refusal(plan, (n_m, e_m), -down_m)
        if why:
            raise FormationError(f"slot {k} (N {n_m:.1f} E {e_m:.1f} alt {-down_m:g} m): {why}")
    pos = np.array([positions_ned_m[vid] for vid in ids], dtype=float)
    if not np.isfinite(pos).all():
        raise FormationError("a vehicle reported a non-finite position: nothing sent")
    key = spec.key(ids)
    kept = memory.recall(key) if memory is not None and not reassign else None
    if (
        kept is not None
        and sorted(kept) == list(ids)
        and sorted(kept.values()) == list(range(len(ids)))
    ):
        slot_of = np.array([kept[vid] for vid in ids])
    else:
        kept = None
        slot_of = assign(pos, slots)
    targets, moved = _as_flown(
        plan, separation_m, ids, slot_of, slots[slot_of], pos_sigma_m or {}, spacing_m=d_m
    )
    _check_berths(ids, targets, separation_m, pos_sigma_m or {}, spec.spacing_m)
    if memory is not None:
        memory.remember(key, dict(zip(ids, slot_of.tolist(), strict=True)))
    return FormationPlan(ids, tuple(slot_of.tolist()), targets, pos, kept is not None, moved)


def _as_flown(
    plan: FleetPlan | None,
    separation_m: float,
    ids: tuple[int, ...],
    slot_of: np.ndarray,
    targets_ned_m: np.ndarray,
    pos_sigma_m: Mapping[int, float],
    *,
    spacing_m: float,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """(targets, moved) as each vehicle would fly its slot (groundstation/target_check.py): a
    slot it would refuse refuses the formation, naming the vehicle and why; moved slots must
    keep `spacing_m` (the planned slots' closest pair: the spacing, at least the separation)
    from every other slot, or the formation is refused. Nothing is sent either way."""
    if plan is None or (not plan.keep_out and plan.fence is None):
        return targets_ned_m, ("",) * len(ids)
    from groundstation.target_check import TargetCheck  # shapely and scipy: only with a plan

    check = TargetCheck(plan, separation_m)
    out = targets_ned_m.copy()
    moved = []
    for i, (vid, t) in enumerate(zip(ids, targets_ned_m.tolist(), strict=True)):
        sigma_m = float(pos_sigma_m.get(vid, 0.0))
        verdict = check.check(t, sigma_m)
        if verdict.refused:
            raise FormationError(
                f"vehicle {vid} would refuse slot {int(slot_of[i])} (N {t[0]:.1f} E {t[1]:.1f} "
                f"alt {-t[2]:g} m, position sigma {sigma_m:g} m): {verdict.refused}; nothing sent"
            )
        out[i] = verdict.target_ned_m
        moved.append(verdict.moved)
    if not any(moved):
        return out, tuple(moved)
    for i in (k for k, why in enumerate(moved) if why):
        d = np.linalg.norm(out - out[i], axis=1)
        d[i] = np.inf
        j = int(np.argmin(d))
        if d[j] < spacing_m - 1e-6:
            raise FormationError(
                f"vehicle {ids[i]}'s slot {int(slot_of[i])} would be moved ({moved[i]}) to "
                f"{d[j]:.2f} m from vehicle {ids[j]}'s slot {int(slot_of[j])}, closer than the "
                f"formation's {spacing_m:.2f} m spacing (move the formation off the zone); "
                "nothing sent"
            )
    return out, tuple(moved)


def _check_berths(
    ids: tuple[int, ...],
    targets_ned_m: np.ndarray,
    separation_m: float,
    pos_sigma_m: Mapping[int, float],
    spacing_m: float,
) -> None:
    """Refuse a formation whose vehicles could not hold their slots: two slots nearer than
    the berth the two vehicles' filters keep between their estimates at the position sigmas
    they report (policy.safety.pair_radius_m: the separation with its margin plus sigma_k
    sqrt(sigma_i^2 + sigma_j^2), the filter's defaults; 6.4 m at 3 m on plain 0.5 m GNSS).
    They would push each other off their slots for as long as they hover there, and a crowd
    held inside its berth is where true positions come within the separation (docs/sky.md,
    "Beyond the preset"). The message says the spacing that would hold."""
    sig = np.array([max(0.0, float(pos_sigma_m.get(vid, 0.0))) for vid in ids])
    if len(ids) < 2 or not sig.any():
        return  # exact positions: the separation check of the slots is the berth's
    from policy.safety import SafetyConfig, pair_radius_m

    cfg = SafetyConfig(radius_m=separation_m)
    d = np.linalg.norm(targets_ned_m[:, None, :2] - targets_ned_m[None, :, :2], axis=2)
    berth, _ = pair_radius_m(cfg, sig, np.broadcast_to(sig, (len(ids), len(ids))))
    berth = np.asarray(berth, float)
    np.fill_diagonal(d, np.inf)
    short = d < berth - 1e-6
    if not short.any():
        return
    ratio = np.where(short, berth / np.maximum(d, 1e-9), 0.0)
    i, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    need_m = spacing_m * float(ratio[i, j]) if spacing_m > 0 else float(berth[i, j])
    raise FormationError(
        f"vehicles {ids[i]} and {ids[j]} would hover {d[i, j]:.1f} m apart, inside the "
        f"{berth[i, j]:.1f} m their filters keep between estimates at the position sigmas they "
        f"report ({sig[i]:g} m, {sig[j]:g} m): they could not hold their slots; widen "
        f"--spacing-m to {math.ceil(need_m * 10) / 10:g} m or fly with a better position fix; "
        "nothing sent"
    )


def load_slots(path: str) -> tuple[tuple[float, float], ...]:
    """A slot file: JSON `{"slots_fr_m": [[forward, right], ...]}` (metres from the centre; at
    heading 0 forward is north and right east). BadFileError or FormationError: one line."""
    what = "slot file"
    raw = read_bounded(path, MAX_SLOT_FILE_BYTES, what)
    doc = parse_json(decode_utf8(raw, what), what)
    slots = doc.get("slots_fr_m") if isinstance(doc, dict) else None
    if not isinstance(slots, list) or not slots:
        raise FormationError(
            f'{what} {path}: expected {{"slots_fr_m": [[forward_m, right_m], ...]}}'
        )
    if len(slots) > MAX_SLOTS:
        raise FormationError(f"{what} {path}: {len(slots)} slots, at most {MAX_SLOTS}")
    out = []
    for k, s in enumerate(slots):
        ok = (
            isinstance(s, list)
            and len(s) == 2
            and all(isinstance(c, int | float) and not isinstance(c, bool) for c in s)
            and all(math.isfinite(c) and abs(c) <= 10_000 for c in s)
        )
        if not ok:
            raise FormationError(
                f"{what} {path}: slot {k} is {s!r}, expected [forward_m, right_m] finite within 10 km"
            )
        out.append((float(s[0]), float(s[1])))
    return tuple(out)
