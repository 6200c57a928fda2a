"""Mission files -> Mission items: covey's own JSON and QGroundControl `.plan` files.

Both are read through kit/safe_load.py (size, nesting) and checked item by item; anything a
vehicle could not fly, or that covey does not fly, is refused as one line naming the item
(MissionFileError), so that nothing is sent from a file that was half understood.

Altitudes, as everywhere an operator reads one, are up in metres with their datum said:

    covey JSON   {"mission_id": 7, "items": [
                   {"kind": "takeoff", "alt_m": 10},                          above the origin
                   {"kind": "waypoint", "north_m": 20, "east_m": 5, "alt_m": 10,
                    "speed_m_s": 2, "hold_s": 3},                             above the origin
                   {"kind": "waypoint", "lat_deg": 48.75, "lon_deg": 9.1,
                    "alt_amsl_m": 470},                                       AMSL
                   {"kind": "hold", "hold_s": 5}, {"kind": "land"} | {"kind": "return"}]}
    QGC .plan    mission.items (SimpleItem): NAV_WAYPOINT 16, NAV_LOITER_TIME 19 (a waypoint with
                 its wait), NAV_RETURN_TO_LAUNCH 20, NAV_LAND 21 (at a position: a waypoint
                 there, then land), NAV_TAKEOFF 22; frames GLOBAL (AMSL) and GLOBAL_RELATIVE_ALT
                 (above QGC's planned home, whose AMSL altitude makes them AMSL). A take-off's
                 altitude is taken above the home, which is where the fleet takes off.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

from comms.geo import GeoOrigin, mission_route_ned_m
from comms.schema import (
    MAX_MISSION_ITEMS,
    DecodeError,
    MissionFrame,
    MissionItem,
    MissionItemKind,
)
from kit.safe_load import BadFileError, decode_utf8, parse_json, read_bounded

MAX_MISSION_FILE_BYTES = 1_000_000
"""A mission file larger than this is refused unread (a QGC plan of 100 items is ~40 KB)."""

K = MissionItemKind
QGC_WAYPOINT, QGC_LOITER_TIME, QGC_RTL, QGC_LAND, QGC_TAKEOFF = 16, 19, 20, 21, 22
QGC_FRAME_GLOBAL, QGC_FRAME_RELATIVE = (0, 5), (3, 6)
"""MAV_FRAME_GLOBAL(_INT): AMSL; MAV_FRAME_GLOBAL_RELATIVE_ALT(_INT): above the home."""


class MissionFileError(BadFileError):
    """A mission file cannot be flown; the message is one line that says why."""


@dataclass(frozen=True)
class MissionFile:
    """What a mission file holds."""

    items: tuple[MissionItem, ...]
    mission_id: int = 1
    """The file's `mission_id` (covey JSON), else 1."""


@dataclass(frozen=True)
class MissionRequest:
    """A checked mission, not yet addressed or stamped (the station's upload job; what a
    CommandRequest is to a command)."""

    items: tuple[MissionItem, ...]
    mission_id: int = 1

    def describe(self) -> str:
        return f"mission {self.mission_id} upload ({len(self.items)} items)"

    def route_ned_m(self, origin: GeoOrigin) -> list[tuple[float, float, float]]:
        """The waypoints' positions in local NED, in order (what the station draws)."""
        return mission_route_ned_m(self.items, origin)


def load_mission_file(path: str | os.PathLike[str]) -> MissionFile:
    """The items of a covey mission JSON or a QGC `.plan` file (told apart by their content)."""
    what = f"mission file {Path(path).name}"
    raw = read_bounded(path, MAX_MISSION_FILE_BYTES, what)
    return mission_from_text(decode_utf8(raw, what), what)


def mission_from_text(text: str, what: str = "mission") -> MissionFile:
    """As `load_mission_file`, from the file's text (the station's upload field)."""
    doc = parse_json(text, what)
    return MissionFile(parse_mission(doc, what), mission_id_of(doc))


def parse_mission(doc: object, what: str = "mission") -> tuple[MissionItem, ...]:
    """Items from a parsed covey JSON or QGC plan document; MissionFileError says why not."""
    if not isinstance(doc, dict):
        raise MissionFileError(f"{what}: expected a JSON object")
    if doc.get("fileType") == "Plan" or "mission" in doc:
        items = _qgc(doc, what)
    elif "items" in doc:
        items = _covey(doc, what)
    else:
        raise MissionFileError(f"{what}: neither a covey mission ('items') nor a QGC plan")
    if not 1 <= len(items) <= MAX_MISSION_ITEMS:
        raise MissionFileError(
            f"{what}: {len(items)} items, a mission holds 1..{MAX_MISSION_ITEMS}"
        )
    for i, item in enumerate(items):
        try:
            item.validate(i)
        except DecodeError as exc:
            raise MissionFileError(f"{what}: {exc}") from None
    return tuple(items)


def mission_id_of(doc: object, default: int = 1) -> int:
    """The file's `mission_id` (covey JSON), else `default`."""
    v = doc.get("mission_id", default) if isinstance(doc, dict) else default
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**32:
        raise MissionFileError(f"mission_id {v!r} must be an integer within 0..2^32-1")
    return v


def shifted(items: tuple[MissionItem, ...], east_m: float) -> tuple[MissionItem, ...]:
    """The items with every waypoint moved `east_m` metres east (a copy of one route for the next
    vehicle, beside it rather than on top of it)."""
    if not east_m:
        return items
    out = []
    for item in items:
        if item.kind is not K.WAYPOINT:
            out.append(item)
        elif item.frame is MissionFrame.LOCAL:
            out.append(replace(item, y=item.y + east_m))
        else:
            lat, lon, _ = GeoOrigin(item.x, item.y, 0.0).to_global(0.0, east_m, 0.0)
            out.append(replace(item, x=lat, y=lon))
    return tuple(out)


# -- covey JSON ----------------------------------------------------------------------------------
_COVEY_KEYS = {
    "takeoff": {"kind", "alt_m"},
    "waypoint": {
        "kind",
        "north_m",
        "east_m",
        "alt_m",
        "lat_deg",
        "lon_deg",
        "alt_amsl_m",
        "speed_m_s",
        "hold_s",
    },
    "hold": {"kind", "hold_s"},
    "land": {"kind"},
    "return": {"kind"},
}


def _num(d: dict, key: str, where: str, default: float | None = None) -> float:
    v = d.get(key, default)
    if v is None:
        raise MissionFileError(f"{where}: needs {key!r}")
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise MissionFileError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def _covey(doc: dict, what: str) -> list[MissionItem]:
    mission_id_of(doc)
    raw = doc["items"]
    if not isinstance(raw, list):
        raise MissionFileError(f"{what}: 'items' must be a list")
    if len(raw) > MAX_MISSION_ITEMS:
        raise MissionFileError(f"{what}: {len(raw)} items, a mission holds 1..{MAX_MISSION_ITEMS}")
    out = []
    for k, d in enumerate(raw, 1):
        where = f"{what} item {k}"
        if not isinstance(d, dict) or d.get("kind") not in _COVEY_KEYS:
            raise MissionFileError(
                f"{where}: needs a 'kind' of {', '.join(_COVEY_KEYS)}, got {str(d)[:40]}"
            )
        kind = d["kind"]
        unknown = set(d) - _COVEY_KEYS[kind]
        if unknown:
            raise MissionFileError(f"{where}: unknown fields {', '.join(sorted(unknown))}")
        if kind == "takeoff":
            out.append(MissionItem(K.TAKEOFF, alt_m=_num(d, "alt_m", where)))
        elif kind == "hold":
            out.append(MissionItem(K.HOLD, hold_s=_num(d, "hold_s", where)))
        elif kind == "land":
            out.append(MissionItem(K.LAND))
        elif kind == "return":
            out.append(MissionItem(K.RETURN))
        else:
            speed, hold = _num(d, "speed_m_s", where, 0.0), _num(d, "hold_s", where, 0.0)
            local, world = (
                {"north_m", "east_m", "alt_m"} & set(d),
                {"lat_deg", "lon_deg", "alt_amsl_m"} & set(d),
            )
            if local and world or not (local or world):
                raise MissionFileError(
                    f"{where}: a waypoint is north_m, east_m, alt_m (above the origin) or "
                    "lat_deg, lon_deg, alt_amsl_m, not a mix"
                )
            if local:
                frame, x, y, alt = (
                    MissionFrame.LOCAL,
                    _num(d, "north_m", where),
                    _num(d, "east_m", where),
                    _num(d, "alt_m", where),
                )
            else:
                frame, x, y, alt = (
                    MissionFrame.GLOBAL,
                    _num(d, "lat_deg", where),
                    _num(d, "lon_deg", where),
                    _num(d, "alt_amsl_m", where),
                )
            if alt < 0 and frame is MissionFrame.LOCAL:
                raise MissionFileError(f"{where}: altitude {alt:g} m is below the origin")
            out.append(MissionItem(K.WAYPOINT, frame, x, y, alt, speed, hold))
    return out


# -- QGroundControl .plan ------------------------------------------------------------------------
def _qgc(doc: dict, what: str) -> list[MissionItem]:
    mission = doc.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise MissionFileError(f"{what}: a QGC plan needs mission.items")
    home = mission.get("plannedHomePosition")
    home_amsl_m = None
    if isinstance(home, list) and len(home) == 3 and all(_finite(v) for v in home):
        home_amsl_m = float(home[2])
    raw = mission["items"]
    if len(raw) > MAX_MISSION_ITEMS:
        raise MissionFileError(f"{what}: {len(raw)} items, a mission holds 1..{MAX_MISSION_ITEMS}")
    out: list[MissionItem] = []
    last_amsl_m = None
    for k, d in enumerate(raw, 1):
        where = f"{what} item {k}"
        if not isinstance(d, dict):
            raise MissionFileError(f"{where}: not an object")
        if d.get("type") != "SimpleItem":
            raise MissionFileError(
                f"{where}: {d.get('type')!r} items (surveys, corridors) are not flown by covey"
            )
        cmd, frame, params = d.get("command"), d.get("frame"), d.get("params")
        if not isinstance(params, list) or len(params) != 7:
            raise MissionFileError(f"{where}: params must be a list of 7 values")
        if cmd == QGC_RTL:
            out.append(MissionItem(K.RETURN))
            continue
        if cmd not in (QGC_WAYPOINT, QGC_LOITER_TIME, QGC_LAND, QGC_TAKEOFF):
            raise MissionFileError(
                f"{where}: MAV_CMD {cmd} is not flown by covey (it flies 16 waypoint, 19 loiter "
                "time, 20 return, 21 land, 22 take-off)"
            )
        if frame in QGC_FRAME_GLOBAL:
            rel = False
        elif frame in QGC_FRAME_RELATIVE:
            rel = True
        else:
            raise MissionFileError(
                f"{where}: frame {frame} is not supported (0/5 global AMSL, 3/6 above home)"
            )
        lat, lon, alt = params[4], params[5], params[6]
        if cmd == QGC_TAKEOFF:
            if not _finite(alt):
                raise MissionFileError(f"{where}: take-off altitude {alt!r} is not a number")
            above = float(alt) if rel else _above_home(float(alt), home_amsl_m, where)
            if above <= 0:
                raise MissionFileError(f"{where}: take-off altitude {above:g} m is not above home")
            out.append(MissionItem(K.TAKEOFF, alt_m=above))
            if home_amsl_m is not None:
                last_amsl_m = home_amsl_m + above
            continue
        if cmd == QGC_LAND and (lat in (0, None) or lon in (0, None)):
            out.append(MissionItem(K.LAND))
            continue
        if not (_finite(lat) and _finite(lon) and _finite(alt)):
            raise MissionFileError(f"{where}: latitude, longitude and altitude must be numbers")
        if cmd == QGC_LAND:  # land at a position: fly there at the last altitude, then land
            amsl = (
                last_amsl_m
                if last_amsl_m is not None
                else _amsl(float(alt), rel, home_amsl_m, where)
            )
            out.append(MissionItem(K.WAYPOINT, MissionFrame.GLOBAL, float(lat), float(lon), amsl))
            out.append(MissionItem(K.LAND))
            continue
        amsl = _amsl(float(alt), rel, home_amsl_m, where)
        if home_amsl_m is not None and amsl < home_amsl_m:
            raise MissionFileError(f"{where}: altitude {amsl - home_amsl_m:g} m is below home")
        hold = params[0] if _finite(params[0]) else 0.0
        out.append(
            MissionItem(
                K.WAYPOINT, MissionFrame.GLOBAL, float(lat), float(lon), amsl, 0.0, float(hold)
            )
        )
        last_amsl_m = amsl
    return out


def _finite(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _amsl(alt: float, relative: bool, home_amsl_m: float | None, where: str) -> float:
    if not relative:
        return alt
    if home_amsl_m is None:
        raise MissionFileError(
            f"{where}: an altitude above home needs mission.plannedHomePosition [lat, lon, alt]"
        )
    return home_amsl_m + alt


def _above_home(alt_amsl: float, home_amsl_m: float | None, where: str) -> float:
    if home_amsl_m is None:
        raise MissionFileError(
            f"{where}: an AMSL take-off altitude needs mission.plannedHomePosition [lat, lon, alt]"
        )
    return alt_amsl - home_amsl_m
