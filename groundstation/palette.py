"""Colours the operator learns once: one per flight mode, plus alert colours (RGB 0-255).

Shared by the browser ground station and the Foxglove channels (recordings and the live bridge),
so that a vehicle has the same colour everywhere."""

from __future__ import annotations

from comms.schema import Mode

MODE_RGB: dict[Mode, tuple[int, int, int]] = {
    Mode.LANDED: (130, 130, 130),
    Mode.TAKING_OFF: (0, 170, 220),
    Mode.HOLDING: (40, 90, 230),
    Mode.GOTO: (20, 170, 70),
    Mode.LANDING: (235, 140, 0),
    Mode.RETURNING: (150, 60, 200),
    Mode.KILLED: (20, 20, 20),
    Mode.MISSION: (0, 150, 140),
}
UNKNOWN_RGB = (190, 190, 190)
LOST_RGB = (200, 200, 200)
ALERT_RGB = (230, 30, 30)
RING_OK_RGB = (90, 160, 90)
GEOFENCE_RGB = (230, 120, 0)
KEEP_OUT_RGB = (200, 30, 30)
"""Keep-out zones of the fleet plan (comms/plan.py): red, drawn translucent on the ground."""
GOAL_RGB = (255, 200, 0)
TRAFFIC_RGB = (220, 0, 160)
"""Traffic that does not cooperate (agent/traffic.py): magenta, a colour no mode uses."""


def mode_rgb(mode: Mode | None) -> tuple[int, int, int]:
    return MODE_RGB.get(mode, UNKNOWN_RGB) if mode is not None else UNKNOWN_RGB


def css(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)
