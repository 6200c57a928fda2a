"""How covey's own ADSB_VEHICLE reports are told from real traffic, and which emitters are manned.

In onboard (relay) mode covey forwards each neighbour to PX4 as an ADSB_VEHICLE report, the same
MAVLink message (and PX4 `transponder_report` topic) that a real ADS-B or FLARM receiver feeds.
PX4 streams every held report back out, so the relay hears covey's neighbours and real traffic
mixed. A report is covey's own (a cooperative fleet member) when all of these hold:

    ICAO address in covey's block   COVEY_ICAO_BASE | vehicle_id (bit 24 set: outside the 24-bit
                                    space every real transponder's address lives in)
    callsign starts with            "CVY" (then the vehicle id)
    emitter type                    UAV (14)

Any other report is traffic that does not cooperate: the relay forwards it as traffic, PX4's
covey module flies around it with full responsibility. Real ADS-B cannot carry an address above
0xFFFFFF, so it is never taken for a fleet member; covey's own reports are never echoed back to
the mesh as traffic. The C twin is `covey_traffic_is_covey` (firmware/covey_traffic.c), parity
tested. Traffic that the relay forwards from the mesh to PX4 (an intruder a station reports)
keeps its own address and a "TRF" callsign: PX4 treats it as traffic, and the relay does not
read its echo back as new traffic (agent/backends/relay.py).
"""

from __future__ import annotations

COVEY_ICAO_BASE = 0x0100_0000
"""Covey vehicle v reports itself as ICAO address COVEY_ICAO_BASE | v (v < 2**16)."""
COVEY_ICAO_MASK = 0xFFFF_0000
COVEY_CALLSIGN_PREFIX = "CVY"
TRAFFIC_CALLSIGN_PREFIX = "TRF"
"""Callsign of mesh traffic forwarded to the autopilot (not a fleet member)."""
EMITTER_UAV = 14
"""MAVLink ADSB_EMITTER_TYPE_UAV."""
MANNED_EMITTERS = frozenset({1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12})
"""ADSB_EMITTER_TYPE values of aircraft with people aboard: light, small, large, high-vortex
large, heavy, highly manoeuvrable, rotorcraft, glider, lighter than air, parachute, ultralight.
UAV, space, surface vehicles, obstacles and 'no information' are not."""


def covey_icao(vehicle_id: int) -> int:
    """The ICAO address covey vehicle `vehicle_id` is reported under."""
    if not 0 < vehicle_id < 0x1_0000:
        raise ValueError(f"vehicle id {vehicle_id} does not fit covey's ICAO block (1..65535)")
    return COVEY_ICAO_BASE | vehicle_id


def covey_callsign(vehicle_id: int) -> str:
    return f"{COVEY_CALLSIGN_PREFIX}{vehicle_id}"


def is_covey_report(icao_address: int, callsign: str, emitter_type: int) -> bool:
    """Whether an ADSB_VEHICLE report is one of covey's own neighbour reports."""
    return (
        icao_address & COVEY_ICAO_MASK == COVEY_ICAO_BASE
        and callsign.startswith(COVEY_CALLSIGN_PREFIX)
        and int(emitter_type) == EMITTER_UAV
    )


def vehicle_of_report(icao_address: int) -> int:
    """The covey vehicle id behind a covey report's address."""
    return icao_address & ~COVEY_ICAO_MASK & 0xFFFF_FFFF


def is_manned(emitter_type: int) -> bool:
    return int(emitter_type) in MANNED_EMITTERS
