"""Operator input -> commands, with a clear message for every bad value (no Command is built).

The GUI and `covey cmd` both go through here, so a value that the wire would reject (non-finite,
out of range) is caught at the ground station and explained, before anything is sent.

One altitude convention wherever an operator types or reads one: altitude UP, in metres, with its
datum said. Take-off and local gotos are above the fleet origin (local NED 0,0,0, on the ground
where the fleet takes off); global gotos are AMSL (the datum of the fleet origin's altitude,
comms/geo.py). NED, with its down axis, exists only inside: `goto_local` turns the altitude into
the wire's down coordinate here, and `describe` turns it back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from comms.schema import (
    GLOBAL_ALT_RANGE_M,
    LOCAL_DOWN_RANGE_M,
    MAX_VEHICLE_ID,
    TAKEOFF_ALT_RANGE_M,
    CommandKind,
)


class InputError(ValueError):
    """An operator input is invalid; str() is a message to show as is."""


@dataclass(frozen=True)
class CommandRequest:
    """A validated command, not yet addressed or stamped."""

    kind: CommandKind
    params: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def describe(self) -> str:
        return describe(self.kind, self.params)


def _m(x: float) -> str:
    """Metres to one decimal, without a "-0.0" (1e-15 from a float round trip reads 0.0)."""
    return f"{x if abs(x) >= 0.05 else 0.0:.1f}"


def describe(kind: CommandKind, params: tuple[float, float, float]) -> str:
    """What a command asks, as an operator reads it: rounded, altitude up with its datum."""
    p = params
    if kind is CommandKind.TAKEOFF:
        return f"takeoff to {_m(p[0])} m above origin"
    if kind is CommandKind.GOTO_LOCAL:
        return f"goto N {_m(p[0])} E {_m(p[1])} alt {_m(-p[2])} m above origin"
    if kind is CommandKind.GOTO_GLOBAL:
        return f"goto lat {p[0]:.6f} lon {p[1]:.6f} alt {_m(p[2])} m AMSL"
    return kind.name.lower().replace("_", " ")


def number(name: str, raw: object, lo: float, hi: float, unit: str = "") -> float:
    """`raw` (a float from a GUI field, or text) as a finite float within [lo, hi]."""
    if isinstance(raw, bool) or raw is None:
        raise InputError(f"{name}: enter a number")
    try:
        value = float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name}: {raw!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{name}: must be a finite number, got {raw!r}")
    if not lo <= value <= hi:
        raise InputError(
            f"{name}: {value:g}{unit} is outside the allowed range [{lo:g}, {hi:g}]{unit}"
        )
    return value


def takeoff(alt_m: object) -> CommandRequest:
    """`alt_m`: altitude above the fleet origin, up."""
    alt = number("Take-off altitude above origin", alt_m, *TAKEOFF_ALT_RANGE_M, unit=" m")
    return CommandRequest(CommandKind.TAKEOFF, (alt, 0.0, 0.0))


def goto_local(n_m: object, e_m: object, alt_m: object, limit_m: float = 1000.0) -> CommandRequest:
    """North and east of the fleet origin and `alt_m` above it (up; the wire's down is -alt).
    `limit_m`: how far from the origin a local goal may be (the geofence, or a sane bound)."""
    n = number("North", n_m, -limit_m, limit_m, unit=" m")
    e = number("East", e_m, -limit_m, limit_m, unit=" m")
    lo_m, hi_m = -LOCAL_DOWN_RANGE_M[1], -LOCAL_DOWN_RANGE_M[0]
    alt = number("Altitude above origin", alt_m, lo_m, hi_m, unit=" m")
    if math.hypot(n, e) > limit_m:
        raise InputError(
            f"Goto: ({n:g}, {e:g}) is {math.hypot(n, e):.0f} m from the origin, beyond {limit_m:g} m"
        )
    return CommandRequest(CommandKind.GOTO_LOCAL, (n, e, -alt if alt else 0.0))


def goto_global(lat_deg: object, lon_deg: object, alt_amsl_m: object) -> CommandRequest:
    """`alt_amsl_m`: altitude above mean sea level (the datum of the fleet origin's altitude)."""
    lat = number("Latitude", lat_deg, -90.0, 90.0, unit="°")
    lon = number("Longitude", lon_deg, -180.0, 180.0, unit="°")
    alt = number("Altitude AMSL", alt_amsl_m, *GLOBAL_ALT_RANGE_M, unit=" m")
    return CommandRequest(CommandKind.GOTO_GLOBAL, (lat, lon, alt))


SIMPLE_KINDS = frozenset(
    {
        CommandKind.LAND,
        CommandKind.HOLD,
        CommandKind.RETURN,
        CommandKind.KILL,
        CommandKind.MISSION_START,
        CommandKind.MISSION_PAUSE,
        CommandKind.MISSION_RESUME,
        CommandKind.MISSION_ABORT,
        CommandKind.MISSION_STATUS,
    }
)
"""The commands without parameters."""


def simple(kind: CommandKind) -> CommandRequest:
    if kind not in SIMPLE_KINDS:
        raise InputError(f"{kind.name} needs parameters")
    return CommandRequest(kind)


def targets(text: str, known: set[int] | None = None) -> tuple[int, ...]:
    """Parse "all" (-> ()), "3", "1,2,5" or "1-4" into sorted vehicle ids.

    With `known`, ids that are not in the fleet are refused (a typo must not address nobody).
    """
    text = (text or "").strip().lower()
    if text in ("all", "*"):
        return ()
    if not text:
        raise InputError("Targets: enter 'all' or vehicle ids like 1,2,5 or 1-4")
    ids: set[int] = set()
    for part in text.replace(" ", "").split(","):
        if not part:
            continue
        lo_s, sep, hi_s = part.partition("-")
        try:
            lo = int(lo_s)
            hi = int(hi_s) if sep else lo
        except ValueError:
            raise InputError(f"Targets: {part!r} is not a vehicle id or a range like 1-4") from None
        if not 1 <= lo <= hi <= MAX_VEHICLE_ID:
            why = (
                "vehicle ids start at 1"
                if lo < 1
                else f"vehicle ids end at {MAX_VEHICLE_ID}"
                if hi > MAX_VEHICLE_ID
                else "a range is low-high"
            )
            raise InputError(f"Targets: {part!r}: {why}")
        if hi - lo > 1024:
            raise InputError(f"Targets: range {part!r} is too long")
        ids.update(range(lo, hi + 1))
    if not ids:
        raise InputError("Targets: enter 'all' or vehicle ids like 1,2,5 or 1-4")
    if known is not None:
        unknown = sorted(ids - known)
        if unknown:
            raise InputError(f"Targets: no vehicle {', '.join(map(str, unknown))} in the fleet")
    return tuple(sorted(ids))
