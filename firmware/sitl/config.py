"""Settings of one emulated autopilot (`covey sitl`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from comms.geo import GeoOrigin
from firmware.sitl.params import VehicleParams


@dataclass(frozen=True)
class SitlConfig:
    """One emulated PX4 vehicle and its MAVLink links."""

    vehicle_id: int = 1
    """MAVLink system id (1..254); also the vehicle's id in the fleet."""
    links: tuple[str, ...] = ("udpout:127.0.0.1:14540",)
    """MAVLink links, like PX4's mavlink instances: `udpout:HOST:PORT` sends to a listener
    (MAVSDK's `udpin://`), `udpin:HOST:PORT` listens and answers whoever spoke last. Every link
    gets all telemetry; commands are taken from any."""
    home: GeoOrigin = field(default_factory=GeoOrigin)
    """Where the vehicle stands at boot; local NED (0, 0, 0) of the emulator is here."""
    onboard: bool = False
    """Fly goto targets with the C policy (firmware.cpolicy), avoiding ADSB_VEHICLE traffic."""
    policy_weights: str | None = None
    """Weights file for the C policy (None: the shipped weights)."""
    separation_m: float = 3.0
    """Separation the onboard guidance keeps (its C filter); the decision period scales with it."""
    policy_separation_m: float | None = None
    """Separation the onboard policy is told to keep (it was trained for 3 m; distances scale by
    this / 3). None: the weights' told share of separation_m (the shipped weights: all of it),
    the filter keeps separation_m, as the agents fly (policy.runtime.told_separation_m)."""
    policy_speed_m_s: float = 1.0
    """Onboard policy cruise speed (the policy's unit speed)."""
    sparse_rule: bool = True
    """Onboard guidance flies the straight line where the vehicle meets at most two others and
    not dead-on, and leaves it to the filter (covey_sparse_choose, PX4 CVY_SPARSE), as the
    agents do."""
    healthy: bool = True
    """Pre-arm checks pass. False emulates a failed sensor: SYS_STATUS reports it, arming is refused."""
    params: VehicleParams = field(default_factory=VehicleParams)
    """Airframe and autopilot settings."""
    physics_hz: float = 50.0
    """Integration and receive rate of the real-time loop."""
    position_hz: float = 20.0
    """Rate of GLOBAL_POSITION_INT, LOCAL_POSITION_NED and ATTITUDE."""
    traffic_timeout_s: float = 5.0
    """Traffic reports older than this are forgotten."""
    policy_hz: float = 10.0
    """Rate at which onboard guidance evaluates the policy."""
    duration_s: float | None = None
    """Stop after this long (None: run until stopped)."""
    vehicle_model: str = "ideal"
    """How real the airframe flies (policy.pointmass.VehicleModel): ideal (the setpoint within
    MPC_ACC_HOR, exact positions) or realistic (0.3 s lag, gusts, GNSS drifting 0.5 m: the
    position messages carry the estimate, GPS_RAW_INT h_acc its 1-sigma)."""

    def __post_init__(self) -> None:
        if not 1 <= self.vehicle_id <= 254:
            raise ValueError(
                f"vehicle_id must be within 1..254 (a MAVLink system id), got {self.vehicle_id}"
            )
        if not self.links:
            raise ValueError("at least one MAVLink link is needed")
        from policy.pointmass import VehicleModel

        VehicleModel.named(self.vehicle_model)  # a ValueError that says what is wrong
        for name in (
            "physics_hz",
            "position_hz",
            "traffic_timeout_s",
            "policy_hz",
            "separation_m",
            "policy_speed_m_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        ps = self.policy_separation_m
        if ps is not None and not (math.isfinite(ps) and ps > 0):
            raise ValueError(f"policy_separation_m must be a positive number (or None), got {ps}")
