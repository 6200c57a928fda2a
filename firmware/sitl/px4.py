"""PX4's flight modes and MAVLink conventions, as MAVSDK expects to see them."""

from __future__ import annotations

import enum
from dataclasses import dataclass

# MAV_RESULT values (MAVLink common).
ACCEPTED = 0
TEMPORARILY_REJECTED = 1
"""PX4 answers this when the state forbids the command now (arming checks, mode switches)."""
DENIED = 2
"""PX4 answers this for invalid parameters."""
UNSUPPORTED = 3
FAILED = 4

KILL_MAGIC = 21196.0
"""ARM_DISARM param2 that forces a disarm in the air (MAVSDK `kill`)."""


@dataclass(frozen=True)
class Px4Result:
    """How a command went: a MAV_RESULT value and, if refused, PX4-style words why."""

    result: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.result == ACCEPTED


OK = Px4Result(ACCEPTED)
"""The outcome of every command that went through."""


class Px4Mode(enum.Enum):
    """PX4 flight modes as (main mode, sub mode); MAVLink's custom_mode = main<<16 | sub<<24."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    READY = (4, 1)
    TAKEOFF = (4, 2)
    HOLD = (4, 3)
    """AUTO_LOITER: hold position; DO_REPOSITION flies here too."""
    MISSION = (4, 4)
    RTL = (4, 5)
    LAND = (4, 6)
    OFFBOARD = (6, 0)
    STABILIZED = (7, 0)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @classmethod
    def from_main_sub(cls, main: int, sub: int) -> Px4Mode | None:
        """The mode for a DO_SET_MODE request, or None if PX4 has no such mode."""
        for mode in cls:
            if mode.value == (main, sub):
                return mode
        # PX4 treats AUTO with no sub mode as the current auto mode; we pick HOLD.
        if main == 4 and sub == 0:
            return cls.HOLD
        return None

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> Px4Mode | None:
        return cls.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
