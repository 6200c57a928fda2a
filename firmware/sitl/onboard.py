"""Onboard guidance: the C policy flies goto targets around the traffic the relay forwards.

This is what the PX4 module does on a real Pixhawk: neighbours arrive as ADSB_VEHICLE
(lat/lon/alt, course, horizontal speed), become local positions and velocities, and the policy
turns them into a horizontal velocity setpoint at a fixed rate. With the C policy that is the
module's own tick (covey_guidance_step): the policy decides at its trained period, its velocity
is held in between and the separation filter runs at every tick against the latest traffic.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Protocol

import numpy as np

from comms import adsb
from comms.geo import GeoOrigin
from firmware.sitl.traffic import TrafficStore
from policy.observation import EXACT, Observation, Sky

log = logging.getLogger(__name__)


class OnboardGuidance(Protocol):
    """Onboard guidance: the horizontal velocity to fly toward `goal_ned_m` (onboard mode)."""

    def velocity_ne_m_s(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_m_s: np.ndarray,
        heading_rad: float,
        goal_ned_m: np.ndarray,
        now_s: float,
    ) -> tuple[float, float]: ...


class Policy(Protocol):
    """`firmware.cpolicy.CPolicy` (and `policy.runtime.GuidancePolicy`) look like this."""

    def command(
        self,
        pos_m: Any,
        vel_m_s: Any,
        heading_rad: float,
        goal_m: Any,
        nbr_pos_m: Any,
        nbr_vel_m_s: Any,
        nbr_heading_rad: Any,
    ) -> Any: ...


def load_c_policy(
    weights: str | None,
    separation_m: float,
    cruise_speed_m_s: float,
    policy_separation_m: float | None = None,
    sparse_rule: bool = True,
) -> Policy:
    """The C policy with its filter, which keeps `separation_m`; the network is told
    `policy_separation_m` (None: policy.runtime.told_separation_m, as the agents fly). Imported
    lazily: the emulator runs without it unless onboard mode is asked for."""
    try:
        from firmware.cpolicy import CPolicy
    except ImportError as exc:
        raise RuntimeError(
            f"onboard mode needs firmware.cpolicy (the C policy wrapper): {exc}"
        ) from exc
    from policy.runtime import TOLD_SIGMA_FREE_M, filtered_told_share, told_separation_m

    return CPolicy.load(
        weights,
        separation_m=separation_m,
        cruise_speed_m_s=cruise_speed_m_s,
        policy_separation_m=told_separation_m(
            separation_m, True, policy_separation_m, share=filtered_told_share(weights)
        ),
        sparse_rule=sparse_rule,
        told_sigma_free_m=None if policy_separation_m is not None else TOLD_SIGMA_FREE_M,
    )


class PolicyGuidance:
    """Implements `OnboardGuidance` with a policy and the traffic store.

    A policy with `onboard()` (firmware.cpolicy.CPolicy) flies the C guidance tick: decision
    hold + filter, as the PX4 module does. Any other policy is called at every tick."""

    def __init__(
        self, policy: Policy, traffic: TrafficStore, home: GeoOrigin, rate_hz: float
    ) -> None:
        self.policy, self.traffic, self.home = policy, traffic, home
        self.period_s = 1.0 / rate_hz
        self._next_s = -math.inf
        self._last = (0.0, 0.0)
        onboard = getattr(policy, "onboard", None)
        self._tick = onboard() if callable(onboard) else None
        self.ticks = 0
        """Guidance ticks run."""
        self.decisions = 0
        """Ticks on which the policy decided (C tick: at its trained period)."""
        self.filtered = 0
        """Ticks on which the C filter changed the held velocity."""
        self.cooperative = np.zeros(0, bool)

    def neighbours(self, now_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fresh traffic in the vehicle's local frame: positions (k,2), velocities (k,2), headings (k,)."""
        pos, vel, hdg, coop = [], [], [], []
        for e in self.traffic.fresh(now_s):
            if math.isnan(e.alt_m):
                continue
            n, east, _ = self.home.to_local(e.lat_deg, e.lon_deg, e.alt_m)
            course = 0.0 if math.isnan(e.heading_rad) else e.heading_rad
            # Dead-reckon the report to now: radios are slow (the paper's ran at 3 Hz).
            age_s = max(0.0, now_s - e.received_s)
            v = e.hor_speed_m_s * np.array([math.cos(course), math.sin(course)])
            pos.append(np.array([n, east]) + v * age_s)
            vel.append(v)
            hdg.append(course)
            coop.append(adsb.is_covey_report(e.icao_address, e.callsign, e.emitter_type))
        self.cooperative = np.array(coop, dtype=bool)
        """The last `neighbours` call's cooperative flags: covey's own reports (comms/adsb.py);
        any other traffic does not cooperate, as the PX4 module classifies it."""
        return (
            np.array(pos, dtype=float).reshape(-1, 2),
            np.array(vel, dtype=float).reshape(-1, 2),
            np.array(hdg, dtype=float),
        )

    def velocity_ne_m_s(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_m_s: np.ndarray,
        heading_rad: float,
        goal_ned_m: np.ndarray,
        now_s: float,
    ) -> tuple[float, float]:
        if now_s < self._next_s:
            return self._last
        # Keep the phase (a fixed 10 Hz, not "10 Hz plus the physics step"), never a backlog.
        nxt = self._next_s + self.period_s
        self._next_s = nxt if nxt > now_s else now_s + self.period_s
        nbr_pos, nbr_vel, nbr_hdg = self.neighbours(now_s)
        self.ticks += 1
        if self._tick is not None:
            obs = Observation.shaped(
                pos_ned_m[:2],
                vel_ned_m_s[:2],
                heading_rad,
                goal_ned_m[:2],
                nbr_pos,
                nbr_vel,
                nbr_hdg,
                EXACT if self.cooperative.all() else Sky(nbr_cooperative=self.cooperative),
            )
            r = self._tick.step(obs, now_s)
            if r.status != "ok":
                log.warning("onboard guidance fault: %s", r.status)
                self._last = (math.nan, math.nan)  # the vehicle holds on a non-finite command
                return self._last
            self.decisions += r.decided
            self.filtered += r.filtered
            self._last = (float(r.vel_m_s[0]), float(r.vel_m_s[1]))
            return self._last
        self.decisions += 1
        try:
            cmd = np.asarray(
                self.policy.command(
                    pos_ned_m[:2],
                    vel_ned_m_s[:2],
                    heading_rad,
                    goal_ned_m[:2],
                    nbr_pos,
                    nbr_vel,
                    nbr_hdg,
                ),
                dtype=float,
            ).reshape(-1)
        except (ValueError, ArithmeticError) as exc:  # the core refused its inputs (CPolicyError)
            log.warning("policy fault: %s", exc)
            cmd = np.full(2, math.nan)  # the vehicle holds on a non-finite command
        self._last = (float(cmd[0]), float(cmd[1])) if cmd.shape == (2,) else (math.nan, math.nan)
        return self._last
