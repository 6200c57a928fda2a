"""What a vehicle shell (agent/shell.py) needs: one frozen config for one vehicle or many.

`covey agent --id 3` and `covey agent --ids 1-100` build the same `ShellConfig`; `AgentConfig`
and `FleetSimConfig` are its two presets (one vehicle with the ground-station failsafe on; a
host of simulated vehicles for scale tests without one), kept for the callers that name them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from agent.backends.sim import SimConfig
from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.neighbours import NeighbourConfig
from cli.options import MAX_HOSTED_VEHICLES
from comms.geo import GeoOrigin
from comms.keys import check_vehicle_id
from comms.plan import FleetPlan
from comms.schema import MAX_LINK_TAGS, POSITION_LIMIT_M
from comms.scope import ScopeConfig
from comms.session import MeshConfig
from comms.state_rate import IDLE_STATE_HZ, MAX_HOLD_PERIOD_S, SteadyConfig, check_rates
from comms.traffic import TrafficConfig
from policy.goal_rule import ASSUMED_POS_SIGMA_M
from policy.pointmass import VehicleModel
from policy.tracking import TrackingConfig


@dataclass(frozen=True)
class ShellConfig:
    """The vehicles of one process and how they fly, publish and listen."""

    ids: tuple[int, ...]
    """The vehicle ids, one row each, in start-grid order (`covey agent --ids 1-50,60`)."""
    mesh: MeshConfig = MeshConfig()
    """How the process joins the mesh (one Zenoh session for all its vehicles)."""
    vehicle: str = "sim"
    """What flies: sim (simulated vehicles) | mavsdk:<url> (PX4 via MAVSDK, companion mode) |
    relay:<url> (PX4 runs the policy onboard); a real autopilot is one per process."""
    tick_hz: float = 10.0
    """Guidance (and simulated physics) rate."""
    state_hz: float = 10.0
    """State publishing rate (a radio link may pass fewer; see comms.link)."""
    idle_state_hz: float = IDLE_STATE_HZ
    """State publishing rate while a vehicle is idle: landed (or killed), disarmed, on the
    ground, no autopilot action under way. At least 1 Hz (comms/state_rate.py); back to
    `state_hz` from the tick after a command or arming ends it."""
    idle_tick_hz: float = 2.0
    """Tick rate while every vehicle of the process is idle (as for `idle_state_hz`): a landed
    vehicle waiting costs a fifth of its 10 Hz ticks. A command wakes the loop at once and the
    ticks are back at `tick_hz` from there; never below `idle_state_hz`. `tick_hz`: no resting."""
    calm_tick_hz: float = 3.3
    """Tick rate while every vehicle of the process is calm: flown by the shell, in the air,
    with no neighbour, traffic, zone, fence or goal within what it could reach before a later
    tick (agent/calm.py). On the `tick_hz` grid (every 3rd of 10 Hz), never below the steady
    state rate; `tick_hz`: never calm."""
    hold_tick_hz: float = 1.0
    """Tick rate while every vehicle of the process holds at rest (HOLDING, at most
    comms/state_rate.py HOLD_REST_M_S) and is calm over that longer period's horizon
    (agent/calm.py `holding_at_rest`): a hovering vehicle with nobody near ticks once a
    second (and publishes every other tick, SteadyConfig.hold_state_hz). On the `tick_hz` grid, never below the hold state rate nor
    above `calm_tick_hz`; `calm_tick_hz` or more: no hold tier."""
    steady: SteadyConfig | None = None
    """Publish at the steady rate while receivers can predict the state (hovering, flying
    straight): comms/state_rate.py; None: always at `state_hz` in the air."""
    takeoff_alt_m: float = 10.0
    """Default take-off altitude when a takeoff command gives none."""
    origin: GeoOrigin = GeoOrigin()
    """Fleet origin for goto-global commands."""
    guidance: GuidanceConfig = GuidanceConfig()
    """Separation, speed, arrival and vertical tuning; its `max_neighbours` is how many nearest
    vehicles each policy call sees."""
    neighbours: NeighbourConfig = NeighbourConfig()
    """How long other processes' vehicles stay useful."""
    traffic: TrafficConfig = TrafficConfig()
    """Traffic that does not cooperate (agent/traffic.py): mesh reports and the autopilot's
    ADS-B receiver, flown around as non-cooperative neighbours."""
    traffic_report_hz: float = 2.0
    """How often the traffic an autopilot's receiver hears is reported on the mesh."""
    see_others: bool = True
    """Subscribe to other processes' vehicle states and avoid them too."""
    scope: ScopeConfig = ScopeConfig()
    """Which of them to hear: the grid cells within reach of this process's flying vehicles
    (widened to what `guidance` needs), or the whole fleet with `enabled=False`
    (comms/scope.py, docs/scaling.md)."""
    cell_relay: bool = True
    """One vehicle hears its cells through its router's cell relay when the router has one
    (comms/relay.py): one message a relay period instead of one per neighbour state, a few
    tens of ms later on average. Its own cell subscriptions come back when the relay goes."""
    failsafe: FailsafeConfig = FailsafeConfig()
    """Target checks (geofence, altitude limits) and failsafes."""
    assumed_pos_sigma_m: float = ASSUMED_POS_SIGMA_M
    """Position 1-sigma (m, per horizontal axis) taken for a vehicle whose autopilot reports
    no horizontal accuracy (no GPS_RAW_INT h_acc, no MAVSDK horizontal uncertainty): standard
    GNSS, so that the separation filter pads its pairs and zones (1.8 m + sigma_k x sigma from
    a zone) instead of taking the estimate as exact; 0: as exact (before). Simulated vehicles
    report their model's own."""
    tracking: bool = True
    """Take what the velocity loop did not fly (gusts it does not reject, a loop slower than
    assumed) off the next velocity setpoint (policy/tracking.py); off: setpoints as guidance
    made them."""
    tracking_lag_s: float | None = None
    """The velocity-loop time constant the tracking compensation assumes; None: a simulated
    vehicle's own, 0.3 s for an autopilot (PX4's velocity loop, roughly)."""
    link: str = "perfect"
    """Radio link emulated between this process's one vehicle and the others (comms.link
    spec); one vehicle only."""
    link_tags: int = MAX_LINK_TAGS
    """Keyed mode: tag each state for this many of the vehicle's nearest neighbours, so that
    they check a 64-bit link tag instead of its signature (trust/links.py, docs/security.md);
    0: none (receivers then verify every signature; for a fleet mixing older agents, which
    refuse a tagged state)."""
    open_mode: bool = True
    """False: the shell must sign (it refuses to start on an unkeyed mesh). The published
    OPEN_MODE flag follows the signers the shell really has."""
    trace_guidance: bool = False
    """Publish a GuidanceTrace message after each state (what the policy saw and commanded), so
    that `covey replay --policy` can replay this flight closed-loop exactly; one vehicle only."""
    plan: FleetPlan | None = None
    """A fleet plan to hold from start (`covey agent --plan plan.bin`), checked as one that
    arrives (its signer, in keyed mode); a newer one on the mesh replaces it."""
    sim: SimConfig = SimConfig()
    """Simulated vehicles: point-mass limits (acceleration, climb and descent rates); the start
    fields are set from `start_ne_m` and `spacing_m`."""
    start_ne_m: tuple[float, float] = (0.0, 0.0)
    """Simulated vehicles: north-east corner of the start grid (one vehicle: its start)."""
    spacing_m: float = 8.0
    """Simulated vehicles: the start grid's spacing."""

    def tracking_config(self, model: VehicleModel | None) -> TrackingConfig:
        """The tracking compensation for vehicles flown through `model` (a simulator's), or
        behind a real autopilot (None)."""
        return TrackingConfig.assumed(model, self.tracking, self.tracking_lag_s)

    def __post_init__(self) -> None:
        ids = tuple(self.ids)
        object.__setattr__(self, "ids", ids)  # frozen: a list given is kept as a tuple
        if not 1 <= len(ids) <= MAX_HOSTED_VEHICLES:
            raise ValueError(f"vehicles must be within 1..{MAX_HOSTED_VEHICLES}, got {len(ids)}")
        for vid in ids:
            check_vehicle_id(vid)
        if len(set(ids)) != len(ids):
            raise ValueError("ids must not repeat a vehicle id")
        lag = self.tracking_lag_s
        if lag is not None and not (math.isfinite(lag) and lag >= 0):
            raise ValueError(f"tracking_lag_s must be finite and >= 0 (or None), got {lag}")
        if not (math.isfinite(self.tick_hz) and 0 < self.tick_hz <= 100):
            raise ValueError(f"tick_hz must be within (0, 100], got {self.tick_hz}")
        check_rates(self.state_hz, self.idle_state_hz)
        if not (math.isfinite(self.calm_tick_hz) and 0 < self.calm_tick_hz <= 100):
            raise ValueError(f"calm_tick_hz must be within (0, 100], got {self.calm_tick_hz}")
        low = 1.0 / MAX_HOLD_PERIOD_S
        if not (math.isfinite(self.hold_tick_hz) and low <= self.hold_tick_hz <= 100):
            raise ValueError(
                f"hold_tick_hz must be within [{low:g}, 100] (a holder is heard at least every "
                f"{MAX_HOLD_PERIOD_S:g} s), got {self.hold_tick_hz}"
            )
        if not 0 <= self.link_tags <= MAX_LINK_TAGS:
            raise ValueError(f"link_tags must be within 0..{MAX_LINK_TAGS}, got {self.link_tags}")
        if not (math.isfinite(self.idle_tick_hz) and 0 < self.idle_tick_hz <= 100):
            raise ValueError(f"idle_tick_hz must be within (0, 100], got {self.idle_tick_hz}")
        if not (math.isfinite(self.assumed_pos_sigma_m) and self.assumed_pos_sigma_m >= 0):
            raise ValueError(
                f"assumed_pos_sigma_m must be finite and >= 0, got {self.assumed_pos_sigma_m}"
            )
        if not (math.isfinite(self.spacing_m) and self.spacing_m > 0):
            raise ValueError(f"spacing_m must be positive, got {self.spacing_m}")
        far_ne_m = start_grid(len(ids), self.spacing_m, self.start_ne_m)[-1, :2]
        if not all(abs(v) <= POSITION_LIMIT_M for v in (*self.start_ne_m, *far_ne_m)):
            raise ValueError(
                f"the start grid from N {self.start_ne_m[0]:g} E {self.start_ne_m[1]:g} m "
                f"(spacing {self.spacing_m:g} m) leaves the ±{POSITION_LIMIT_M:g} m a state "
                "can carry"
            )
        if self.guidance.max_neighbours is not None and self.guidance.max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0, got {self.guidance.max_neighbours}")
        kind = self.vehicle.partition(":")[0]
        if kind not in ("sim", "mavsdk", "relay"):
            raise ValueError(
                f"unknown vehicle {self.vehicle!r}: use sim, mavsdk:<url> or relay:<url>"
            )
        if len(ids) > 1 and kind != "sim":
            raise ValueError(
                f"vehicle {self.vehicle}: several vehicles are simulated ones; a real autopilot "
                "is one per process"
            )
        if len(ids) > 1 and self.link not in ("", "perfect"):
            raise ValueError("per-vehicle radio links are emulated for one vehicle only")
        if len(ids) > 1 and self.trace_guidance:
            raise ValueError("guidance traces come from one vehicle only")

    @property
    def calm_every(self) -> int:
        """Ticks of the `tick_hz` grid per calm tick: as many as keep at least `calm_tick_hz`
        and the steady state rate (1: never calm)."""
        floor_hz = max(self.calm_tick_hz, self.steady.state_hz if self.steady else 0.0)
        return max(1, int(self.tick_hz / floor_hz + 1e-9))

    @property
    def hold_every(self) -> int:
        """Ticks of the `tick_hz` grid per hold tick (`hold_tick_hz`): at least the hold state
        rate, at least `calm_every` (equal: no hold tier)."""
        floor_hz = max(self.hold_tick_hz, self.steady.hold_state_hz if self.steady else 0.0)
        return max(self.calm_every, int(self.tick_hz / floor_hz + 1e-9))

    @property
    def resting_tick_hz(self) -> float:
        """The tick rate while every vehicle is idle: `idle_tick_hz`, at least `idle_state_hz`,
        at most `tick_hz`."""
        return min(self.tick_hz, max(self.idle_tick_hz, self.idle_state_hz))

    @property
    def vehicles(self) -> int:
        """How many vehicles this process runs."""
        return len(self.ids)

    @property
    def vehicle_id(self) -> int:
        """The first (with one vehicle: the) vehicle id."""
        return self.ids[0]

    @property
    def rate_hz(self) -> float:
        """The tick rate (`covey fleet-sim --rate-hz`)."""
        return self.tick_hz

    def starts_ned_m(self) -> np.ndarray:
        """(n, 3) where simulated vehicles start."""
        return start_grid(len(self.ids), self.spacing_m, self.start_ne_m)


def AgentConfig(vehicle_id: int, **kw: object) -> ShellConfig:  # noqa: N802 - a config preset
    """One vehicle's shell (`covey agent --id N`): the ground-station failsafe on."""
    return ShellConfig(ids=(vehicle_id,), **kw)  # type: ignore[arg-type]


def FleetSimConfig(  # noqa: N802 - a config preset
    vehicles: int = 500,
    first_id: int = 1,
    ids: tuple[int, ...] = (),
    rate_hz: float = 10.0,
    max_neighbours: int | None = 10,
    drop_s: float = 3.0,
    failsafe: FailsafeConfig = FailsafeConfig(require_gcs=False),
    guidance: GuidanceConfig = GuidanceConfig(),
    **kw: object,
) -> ShellConfig:
    """A host of simulated vehicles (`covey fleet-sim`, `covey agent --ids`): ids `ids`, or
    `first_id` .. `first_id + vehicles - 1`; ticks and states at `rate_hz`; each policy call
    sees the nearest `max_neighbours`; other processes' vehicles unheard for `drop_s` are
    forgotten; no ground-station failsafe by default."""
    if not ids:
        if not 1 <= vehicles <= MAX_HOSTED_VEHICLES:
            raise ValueError(f"vehicles must be within 1..{MAX_HOSTED_VEHICLES}, got {vehicles}")
        check_vehicle_id(first_id)
        check_vehicle_id(first_id + vehicles - 1)
        ids = tuple(range(first_id, first_id + vehicles))
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= 100):
        raise ValueError(f"rate_hz must be within (0, 100], got {rate_hz}")
    if max_neighbours is not None and max_neighbours < 0:
        raise ValueError(f"max_neighbours must be >= 0, got {max_neighbours}")
    return ShellConfig(
        ids=tuple(ids),
        tick_hz=rate_hz,
        state_hz=rate_hz,
        guidance=replace(guidance, max_neighbours=max_neighbours),
        neighbours=NeighbourConfig(drop_s=drop_s),
        failsafe=failsafe,
        **kw,  # type: ignore[arg-type]
    )


def start_grid(n: int, spacing_m: float, corner_ne_m: tuple[float, float]) -> np.ndarray:
    """(n, 3) NED start positions on the ground, a square grid filled row by row."""
    side = math.ceil(math.sqrt(n))
    k = np.arange(n)
    return np.stack(
        [
            corner_ne_m[0] + spacing_m * (k // side),
            corner_ne_m[1] + spacing_m * (k % side),
            np.zeros(n),
        ],
        axis=1,
    )
