"""Calm ticks: a vehicle with nothing near ticks at `calm_tick_hz` (3.3 Hz) instead of 10 Hz.

Most of a flying agent's CPU is the tick itself (docs/companion.md, "The floor under one
agent"), and a vehicle in transit or holding with no neighbour, traffic, zone or goal near has
nothing for a 10 Hz tick to do that a 3.3 Hz one would not: the policy decides once a second,
and the separation filter leaves its command alone. So after each tick the shell asks `calm`;
while it holds, the next tick is due a calm period later, on the same 10 Hz grid (kit/ticks.py),
and a command still wakes the loop at once.

A process is calm when every one of its vehicles:

- is flown by the shell (velocity setpoints; never in relay mode, where the autopilot guides),
  armed, in the air, its autopilot link up, HOLDING, in a GOTO, RETURNING or on a MISSION, with
  no autopilot action under way, and the filter neither corrected nor slowed it this tick;
- is further from its goal than the arrival radius plus what it flies in the horizon (it
  arrives on a 10 Hz tick) and, with a circular geofence, further inside it than that;
- has every neighbour, covey vehicle or traffic, whose closest approach within the filter's
  time horizon, both flying on at their velocities now (`closest_approach_m`: the relative
  position p and velocity v, |p + v t*| with t* = clip(-p.v / v.v, 0, time_horizon_s)), is
  further than

      r_ij + g time_horizon_s + (V_i + V_j) H + 1 m

  (r_ij: policy.safety.pair_radius_m, separation, margin and both position uncertainties; g:
  what traffic gains in speed in H at 2.5 m/s^2, 0 for a covey vehicle), and every keep-out
  zone and fence edge further than the zone filter's clearance + sigma_k sigma +
  V_i (time_horizon_s + H) + 1 m,

where H is two calm periods (the calm interval, plus a state that came just after the last
tick). The filter's velocity obstacle for a pair is the cone truncated at its time horizon:
it acts exactly when the closest approach within the horizon is under r_ij, at the velocities
now (the vehicle's measured one, the neighbour's as reported and dead-reckoned); traffic that
speeds up by g brings it at most g time_horizon_s nearer. The third term bounds what both fly
in H: V is at least the cruise speed for a covey vehicle (guidance never commands more; the
vehicle's own is its speed while it holds), traffic's speed plus that gain. Since |v| <= V_i
+ V_j, the straight relative path stays r_ij + 1 m away over the horizon and H more, and the
gap stays above r_ij + 1 m through H whatever either flies. So no pair comes within the
distance at which the filter acts on it during the calm interval while both keep their
velocities. Where one changes its velocity towards the other (a holding neighbour given a
goto, one of two vehicles flying side by side turning in), the calm vehicle sees it at its
next tick: its filter acts at most one calm period (0.3 s) later than at 10 Hz, from at least
r_ij + 1 m, while the vehicle that turned is not calm (its relative velocity puts the pair
within its own bound) and runs its filter at 10 Hz. That is the delay the fleet already flies
with on a 3 Hz radio link, where decisions use neighbour states up to a third of a second old
(docs/policy.md).

Until issue 37's round fourteen the rule took the gap less |v_i - v_j| time_horizon_s, a
bound on the closest approach that ignores direction: a vehicle flying past a neighbour or
away from it (|v_i - v_j| 2 m/s: 8 m more) ticked at 10 Hz for as long as the pair was within
about 14 m, though the filter would never act on it.

The hold tier (`holding_at_rest`, ShellConfig.hold_tick_hz: 1 Hz): where every vehicle of the
process holds at rest and the rule above holds with H two hold periods (2 s), the next tick is
due a hold period later. A holder's own bound is its speed (about 0), so a neighbour's closest
approach must be further than r_ij + V_j 2 s + 1 m: 6.6 m from a holding covey neighbour at
3 m separation and sigma 0 (the demo's 8 m grid is calm at 1 Hz; realistic vehicles, whose
pair distance is 6.4 m at 0.5 m GNSS, are not). A neighbour that sets off towards the holder
at cruise speed is seen at the holder's next tick, at most a second later, from at least r_ij
+ 1 m, while it runs its own filter at 10 Hz from the start (the pair is within its bound); a
command to the holder wakes its loop at once.
"""

from __future__ import annotations

import numpy as np

from agent.flight_core import FlightCore, Observed
from agent.neighbours import NeighbourSnapshot
from comms.schema import Mode
from comms.state_rate import hold_rows
from kit.masks import mode_mask
from policy.safety import pair_radius_m

BUFFER_M = 1.0
"""Added to every calm distance."""
TRAFFIC_ACCEL_M_S2 = 2.5
"""What traffic is assumed to gain in speed per second within the horizon."""

_CALM_MODES = mode_mask((Mode.HOLDING, Mode.GOTO, Mode.RETURNING, Mode.MISSION))
_ARRIVING = mode_mask((Mode.GOTO, Mode.RETURNING, Mode.MISSION))


def holding_at_rest(core: FlightCore, obs: Observed) -> bool:
    """Whether every vehicle of the process holds at rest (HOLDING, its measured speed at most
    HOLD_REST_M_S): the hold tier's condition (ShellConfig.hold_tick_hz), checked with `calm`
    over the hold tier's longer horizon. A holder's own bound in `calm` is its speed, so only
    its neighbours' reach grows with the horizon: a command wakes the loop at once."""
    return bool(hold_rows(core.mode, obs.vel_m_s).all())


def calm(
    core: FlightCore,
    obs: Observed,
    busy: np.ndarray,
    corrected: np.ndarray,
    ext: NeighbourSnapshot,
    horizon_s: float,
) -> bool:
    """Whether every vehicle of the process may tick at the calm rate (the module's rules).
    `busy`: (N,) an autopilot action is under way; `corrected`: (N,) the filter changed or
    slowed the vehicle's command this tick; `ext`: the others, dead-reckoned to now."""
    if not core.velocity_mode or busy.any() or corrected.any():
        return False
    mode = core.mode
    if not (_CALM_MODES[mode].all() and obs.armed.all() and obs.in_air.all()):
        return False
    if not obs.link_ok.all():
        return False
    g, s = core.cfg.guidance, core.safety_cfg
    pos, vel = obs.pos_m, obs.vel_m_s
    speed = np.maximum(np.hypot(vel[:, 0], vel[:, 1]), g.cruise_speed_m_s)
    travel = speed * horizon_s + BUFFER_M
    targets = core.targets()
    if np.isnan(targets[:, 0]).any():
        return False
    arriving = _ARRIVING[mode] & ~core.mission_waiting
    to_goal = np.hypot(targets[:, 0] - pos[:, 0], targets[:, 1] - pos[:, 1])
    if (arriving & (to_goal < g.arrive_radius_m + travel)).any():
        return False
    fence_r = core.cfg.failsafe.geofence_radius_m
    if fence_r and (np.hypot(pos[:, 0], pos[:, 1]) > fence_r - travel).any():
        return False
    tau_s = s.time_horizon_s
    holding = mode == int(Mode.HOLDING)
    own_bound = np.where(holding, np.hypot(vel[:, 0], vel[:, 1]), speed)
    n = len(pos)
    if n > 1 or len(ext):  # the process's other vehicles are neighbours too (a host's rows)
        coop = np.concatenate([np.ones(n, bool), ext.column("cooperative", True)])
        o_pos = np.concatenate([pos, ext.pos_ned_m]) if len(ext) else pos
        o_vel = np.concatenate([vel, ext.vel_ned_m_s]) if len(ext) else vel
        o_speed = np.hypot(o_vel[:, 0], o_vel[:, 1])
        gain = np.where(coop, 0.0, TRAFFIC_ACCEL_M_S2 * horizon_s)  # traffic may speed up
        o_bound = np.where(coop, np.maximum(o_speed, g.cruise_speed_m_s), o_speed + gain)
        o_bound[:n] = own_bound
        closest = closest_approach_m(pos, vel, o_pos, o_vel, tau_s)
        r, _share = pair_radius_m(
            s,
            core.pos_sigma_m[:, None],
            np.concatenate([core.pos_sigma_m, ext.column("pos_sigma_m", 0.0)])[None, :],
            coop[None, :],
            np.concatenate([np.zeros(n, bool), ext.column("manned", False)])[None, :],
        )
        need = (
            r
            + gain[None, :] * tau_s
            + (own_bound[:, None] + o_bound[None, :]) * horizon_s
            + BUFFER_M
        )
        closest[np.arange(n), np.arange(n)] = np.inf  # not itself
        if (closest <= need).any():
            return False
    router = core.router
    if router is not None:
        clear = router.cfg.reach_m + s.sigma_k * core.pos_sigma_m
        look_m = speed * (tau_s + horizon_s) + BUFFER_M
        if (router.edge_distance_m(pos[:, :2]) <= clear + look_m).any():
            return False
    return True


def closest_approach_m(
    pos_m: np.ndarray, vel_m_s: np.ndarray, o_pos_m: np.ndarray, o_vel_m_s: np.ndarray, tau_s: float
) -> np.ndarray:
    """(n, m) the closest horizontal distance of each pair (row i of pos/vel, entry j of
    o_pos/o_vel) within the next `tau_s`, both flying on at their velocities: |p + v t*| with
    p, v the pair's relative position and velocity and t* = clip(-p.v / v.v, 0, tau_s). The
    filter's velocity obstacle holds the pair exactly when this is under its radius
    (policy/safety.py: the cone truncated at the time horizon)."""
    pn = o_pos_m[None, :, 0] - pos_m[:, None, 0]
    pe = o_pos_m[None, :, 1] - pos_m[:, None, 1]
    vn = o_vel_m_s[None, :, 0] - vel_m_s[:, None, 0]
    ve = o_vel_m_s[None, :, 1] - vel_m_s[:, None, 1]
    vv = vn * vn + ve * ve
    t = np.clip(-(pn * vn + pe * ve) / np.where(vv > 0.0, vv, 1.0), 0.0, tau_s)
    return np.hypot(pn + vn * t, pe + ve * t)
