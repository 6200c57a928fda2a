"""The built-in simulator's own autopilot modes (agent/backends/sim.py), as an enum and as the
plain ints and lookup tables its hot paths test against."""

from __future__ import annotations

import enum

from kit.masks import mode_mask


class SimMode(enum.IntEnum):
    """What a simulated autopilot is doing (its own modes, not the agent's)."""

    IDLE = 0
    TAKEOFF = 1
    HOLD = 2
    VELOCITY = 3
    LAND = 4
    FALLING = 5


_IDLE = int(SimMode.IDLE)  # an enum member's attribute lookup costs more than the test
_TAKEOFF, _HOLD, _VELOCITY = int(SimMode.TAKEOFF), int(SimMode.HOLD), int(SimMode.VELOCITY)
_LAND, _FALLING = int(SimMode.LAND), int(SimMode.FALLING)
_POSITIONAL = mode_mask((SimMode.HOLD, SimMode.TAKEOFF, SimMode.LAND))
_COMING_DOWN = mode_mask((SimMode.LAND, SimMode.FALLING))
