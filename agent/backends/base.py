"""The one small interface every vehicle backend implements.

The built-in simulator, the MAVSDK (companion) backend and the MAVLink relay (onboard) backend all
look the same to the agent. What a backend can do is explicit in `capabilities`; a call it cannot
serve raises `NotSupported` (a permanent property of that backend), which is kept apart from
`BackendError` (this call failed now, with a reason) and from NotImplementedError (a gap in covey).
"""

from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

from comms.plan import FleetPlan
from comms.schema import POS_SIGMA_LIMIT_M


class Capability(enum.Enum):
    VELOCITY_SETPOINT = "velocity_setpoint"
    """Accepts NED velocity setpoints: the agent runs the policy (companion mode)."""
    ONBOARD_GUIDANCE = "onboard_guidance"
    """Runs the policy itself: the agent only forwards goto targets (onboard mode)."""
    TRAFFIC_INPUT = "traffic_input"
    """Accepts neighbour states as traffic reports (MAVLink ADSB_VEHICLE)."""
    TRAFFIC_RECEIVER = "traffic_receiver"
    """Hears traffic that does not cooperate (the autopilot's ADS-B receiver): `traffic_tracks`."""
    GEOFENCE = "geofence"
    """Keeps a geofence of its own: `upload_fence` gives it the fleet plan's (a backstop)."""


class NotSupported(Exception):
    """This backend cannot do this, ever (see `VehicleBackend.capabilities`)."""


class BackendError(Exception):
    """The vehicle refused or failed this call now; the message says why."""


def pos_sigma_of(h_acc_m: float) -> float:
    """An autopilot's horizontal accuracy (metres) as Telemetry.pos_sigma_m: 0 (not reported)
    unless a finite positive number, else at most comms.schema.POS_SIGMA_LIMIT_M."""
    if not (math.isfinite(h_acc_m) and h_acc_m > 0.0):
        return 0.0
    return min(float(h_acc_m), POS_SIGMA_LIMIT_M)


@dataclass(frozen=True)
class Telemetry:
    """What the agent needs to know about its own vehicle, in the fleet's local NED frame."""

    stamp_s: float
    """Time of the sample on the agent's clock, in seconds."""
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    heading_rad: float
    """Yaw: 0 = north, positive clockwise."""
    armed: bool
    in_air: bool
    battery_pct: float
    link_ok: bool = True
    """False when the autopilot link is lost (heartbeat timeout)."""
    pos_sigma_m: float = 0.0
    """1-sigma of the horizontal position estimate, per axis, metres (PX4's eph, GPS h_acc, the
    simulator's drift); 0: exact or not reported."""
    onboard_separation_m: float | None = None
    """The separation the autopilot's own filter keeps, where the policy runs onboard (relay:
    the covey PX4 module's CVY_SEP_M, read from the autopilot); None: not known (or no
    onboard filter)."""


@dataclass(frozen=True)
class Traffic:
    """One neighbour as forwarded to an autopilot that runs the policy onboard."""

    vehicle_id: int
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    heading_rad: float
    age_s: float
    cooperative: bool = True
    """A covey vehicle; False: traffic that does not cooperate (agent/traffic.py), which the
    relay forwards under its own address, not covey's (comms/adsb.py)."""
    manned: bool = False
    """Traffic only: a manned aircraft."""


class VehicleBackend(ABC):
    """A vehicle the agent flies. Use as a context manager; `close()` releases the link."""

    capabilities: frozenset[Capability] = frozenset()
    takes_global_targets: bool = False
    """`goto_global` flies a (lat, lon, alt) target as given (no round trip through NED)."""

    def __enter__(self) -> VehicleBackend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def telemetry(self) -> Telemetry | None:
        """Latest sample, or None before the first one arrives."""

    @abstractmethod
    def takeoff(self, alt_m: float) -> None:
        """Arm and climb to `alt_m` above the home position, then hover."""

    @abstractmethod
    def land(self) -> None: ...

    @abstractmethod
    def hold(self) -> None:
        """Stop and keep the current position."""

    @abstractmethod
    def kill(self) -> None:
        """Stop the motors now, in the air or not. The vehicle falls."""

    def set_velocity_ned(self, vel_ned_m_s: Sequence[float], heading_rad: float) -> None:
        """Fly at this NED velocity, facing `heading_rad` (companion mode)."""
        raise NotSupported(f"{type(self).__name__} does not take velocity setpoints")

    def goto_local(self, pos_ned_m: Sequence[float]) -> None:
        """Fly to this local NED position with onboard guidance (onboard mode)."""
        raise NotSupported(f"{type(self).__name__} does not run guidance onboard")

    def goto_global(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Fly to this global position with onboard guidance (see `takes_global_targets`)."""
        raise NotSupported(f"{type(self).__name__} does not take global targets")

    def send_traffic(self, traffic: Sequence[Traffic]) -> None:
        """Tell the autopilot where the neighbours are (onboard mode)."""
        raise NotSupported(f"{type(self).__name__} does not take traffic reports")

    def traffic_tracks(self, now_s: float) -> list:
        """The traffic the autopilot's receiver heard that is not covey's own (agent.traffic
        TrafficTrack list, local NED), new since the last call."""
        raise NotSupported(f"{type(self).__name__} has no traffic receiver")

    def upload_fence(self, plan: FleetPlan) -> None:
        """Give the autopilot the fleet plan's fence (inclusion) and keep-out zones (exclusion)
        as its own geofence, replacing the one it holds; an empty plan clears it. Blocks until
        the autopilot accepted it (BackendError otherwise)."""
        raise NotSupported(f"{type(self).__name__} keeps no geofence of its own")

    def step(self, now_s: float) -> None:  # noqa: B027 - optional hook, no-op by default
        """Advance by one agent tick. The simulator integrates here; real links do nothing."""
