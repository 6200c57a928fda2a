"""ctypes bindings of covey_fence.h: keep-out zones from an autopilot's geofence items, as the
PX4 module loads them from dataman (firmware/px4).

    zones = CFence(lib, [FenceItem(POLYGON_EXCLUSION, 4, n, e), ...], safety_cfg)
    onboard.step(..., zones=zones)      # firmware.csafety.COnboard: covey_guidance_step_zones

Tests: tests/test_px4_sky.py.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

from firmware.csafety import STATUS_NAMES, SafetyConfigC

POLYGON_INCLUSION = 5001
"""MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION (COVEY_FENCE_POLYGON_INCLUSION)."""
POLYGON_EXCLUSION = 5002
CIRCLE_INCLUSION = 5003
CIRCLE_EXCLUSION = 5004
RETURN_POINT = 5000
"""MAV_CMD_NAV_FENCE_RETURN_POINT: not a zone, skipped."""
CIRCLE_VERTICES = 32
"""COVEY_FENCE_CIRCLE_VERTICES (comms/plan_io.py CIRCLE_VERTICES)."""


@dataclass(frozen=True)
class FenceItem:
    """One covey_fence_item_t: a MAVLink fence item in local north/east metres."""

    command: int
    vertex_count: int = 0
    pos_n_m: float = 0.0
    pos_e_m: float = 0.0
    radius_m: float = 0.0


class FenceItemC(ctypes.Structure):
    _fields_ = [
        ("command", ctypes.c_int32),
        ("vertex_count", ctypes.c_int32),
        ("pos_n_m", ctypes.c_float),
        ("pos_e_m", ctypes.c_float),
        ("radius_m", ctypes.c_float),
    ]


def polygon_items(command: int, ring) -> list[FenceItem]:
    """The items of one polygon (K, 2), as a ground station uploads them."""
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
    return [FenceItem(command, len(ring), float(n), float(e)) for n, e in ring]


def bind(lib: ctypes.CDLL) -> None:
    """Declares the fence functions of `lib`."""
    vp = ctypes.c_void_p
    lib.covey_fence_zones.restype = ctypes.c_int
    lib.covey_fence_zones.argtypes = [
        vp,
        ctypes.POINTER(FenceItemC),
        ctypes.c_int32,
        ctypes.POINTER(SafetyConfigC),
        vp,
    ]
    lib.covey_zone_radius_m.restype = ctypes.c_float
    lib.covey_zone_radius_m.argtypes = [ctypes.POINTER(SafetyConfigC)]
    lib.covey_zones_bytes.restype = ctypes.c_uint32
    lib.covey_zones_bytes.argtypes = []


class CFence:
    """Zones prepared by covey_fence_zones; `status` is "ok" or the fault the core returned (then
    no zones are kept, as the PX4 module then flies)."""

    def __init__(self, lib: ctypes.CDLL, items, safety_cfg):
        bind(lib)
        self._lib = lib
        arr = (FenceItemC * max(len(items), 1))(
            *[
                FenceItemC(i.command, i.vertex_count, i.pos_n_m, i.pos_e_m, i.radius_m)
                for i in items
            ]
        )
        self._buf = ctypes.create_string_buffer(lib.covey_zones_bytes())
        # covey_fence_scratch_t: 2 x 512 floats and 64 int32
        scratch = ctypes.create_string_buffer(4 * (2 * 512 + 64))
        cfg = SafetyConfigC.of(safety_cfg)
        st = lib.covey_fence_zones(self._buf, arr, len(items), ctypes.byref(cfg), scratch)
        self.status = STATUS_NAMES.get(st, str(st))
        self.radius_m = float(lib.covey_zone_radius_m(ctypes.byref(cfg)))

    @property
    def ptr(self) -> int:
        """The address of the covey_zones_t (covey_guidance_step_zones takes it)."""
        return ctypes.addressof(self._buf)

    def lines(self, pos_m, vel_m_s, max_speed_m_s: float, pad_m: float = 0.0) -> list:
        """covey_zones_lines of these zones (firmware.czones.CZones.lines)."""
        from firmware import czones

        czones.bind(self._lib)
        return czones.CZones.lines(self, pos_m, vel_m_s, max_speed_m_s, pad_m)
