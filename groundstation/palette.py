"""The ground station's colours: comms.palette, re-exported (the Foxglove channels share it)."""

from __future__ import annotations

from comms.palette import (
    ALERT_RGB,
    GEOFENCE_RGB,
    GOAL_RGB,
    KEEP_OUT_RGB,
    LOST_RGB,
    MODE_RGB,
    RING_OK_RGB,
    TRAFFIC_RGB,
    UNKNOWN_RGB,
    css,
    mode_rgb,
)

__all__ = [
    "ALERT_RGB",
    "GEOFENCE_RGB",
    "GOAL_RGB",
    "KEEP_OUT_RGB",
    "LOST_RGB",
    "MODE_RGB",
    "RING_OK_RGB",
    "TRAFFIC_RGB",
    "UNKNOWN_RGB",
    "css",
    "mode_rgb",
]
