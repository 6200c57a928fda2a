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

import math

import numpy as np

from agent.flight_core import FlightCore, Observed
from agent.neighbours import NeighbourSnapshot
from comms.schema import Mode
from comms.state_rate import hold_rows
from kit.masks import mode_mask
from policy.safety import SafetyConfig, pair_radius_m, pair_radius_one_m

BUFFER_M = 1.0
"""Added to every calm distance."""
TRAFFIC_ACCEL_M_S2 = 2.5
"""What traffic is assumed to gain in speed per second within the horizon."""

_CALM_MODES = mode_mask((Mode.HOLDING, Mode.GOTO, Mode.RETURNING, Mode.MISSION))
_ARRIVING = mode_mask((Mode.GOTO, Mode.RETURNING, Mode.MISSION))
_HOLDING = int(Mode.HOLDING)
_TIE = 1e-9
"""`_calm_one` leaves a distance to the reference where it lies within this share of its terms'
size of its bound: math.hypot and np.hypot each come within an ulp (2e-16) of the true value,
so what they make of one distance differs by far less."""
_DTYPES = {float: np.dtype(float), bool: np.dtype(bool)}
"""The dtype `NeighbourSnapshot.column` gives a column of each fill's type."""
_ORDINARY = 1e100
"""`_calm_one` leaves to the reference a vehicle with values this large (or NaN): their
products could overflow."""


def holding_at_rest(core: FlightCore, obs: Observed) -> bool:
    """Whether every vehicle of the process holds at rest (HOLDING, its measured speed at most
    HOLD_REST_M_S): the hold tier's condition (ShellConfig.hold_tick_hz), checked with `calm`
    over the hold tier's longer horizon. A holder's own bound in `calm` is its speed, so only
    its neighbours' reach grows with the horizon: a command wakes the loop at once. One vehicle
    that does not hold (the agent in flight: every tick) is answered without array maths."""
    if len(core.mode) == 1 and core.mode[0] != _HOLDING:
        return False
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
    slowed the vehicle's command this tick; `ext`: the others, dead-reckoned to now.

    One vehicle (an agent's process, every tick) is answered in plain floats (`_calm_one`: a
    tenth of the arrays' cost where a neighbour is near, half with 30 far), several by
    `calm_reference`, which also answers the rare case the plain floats leave open (a distance
    on its bound to the last bits): the same answer either way (tests/test_calm_ticks.py)."""
    if len(obs.pos_m) == 1:
        one = _calm_one(core, obs, busy, corrected, ext, horizon_s)
        if one is not None:
            return one
    return calm_reference(core, obs, busy, corrected, ext, horizon_s)


def calm_reference(
    core: FlightCore,
    obs: Observed,
    busy: np.ndarray,
    corrected: np.ndarray,
    ext: NeighbourSnapshot,
    horizon_s: float,
) -> bool:
    """`calm` for any number of vehicles, as arrays: the reference its one-vehicle path
    (`_calm_one`) is tested against."""
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
            core.pos_sigma_m,  # (n,): each row its own (pair_radius_m adds the axis)
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


def _calm_one(
    core: FlightCore,
    obs: Observed,
    busy: np.ndarray,
    corrected: np.ndarray,
    ext: NeighbourSnapshot,
    horizon_s: float,
) -> bool | None:
    """`calm_reference` of a process with one vehicle, in plain floats and cheapest check first:
    its flags, its goal and fence, each neighbour (the first one near ends it), the zones. None
    where a distance lies within _TIE of its bound or is not finite: math.hypot and np.hypot
    may differ in the last bit there (every other operation is the reference's, in its order),
    and the reference decides."""
    if not core.velocity_mode or busy[0] or corrected[0]:
        return False
    mode = int(core.mode[0])
    if not (_CALM_MODES[mode] and obs.armed[0] and obs.in_air[0] and obs.link_ok[0]):
        return False
    target = core.hold_m[0] if mode == _HOLDING else core.goal_m[0]  # targets(), calm modes
    tn_m, te_m = target[:2].tolist()
    if tn_m != tn_m:  # NaN: none
        return False
    g, s = core.cfg.guidance, core.safety_cfg
    pn_m, pe_m = obs.pos_m[0, :2].tolist()
    vn_m_s, ve_m_s = obs.vel_m_s[0, :2].tolist()
    tau_s = s.time_horizon_s
    own_sigma_m = float(core.pos_sigma_m[0])
    size = abs(pn_m) + abs(pe_m) + abs(vn_m_s) + abs(ve_m_s) + abs(own_sigma_m)
    if not (
        size + abs(g.cruise_speed_m_s) + horizon_s + tau_s < _ORDINARY
        and min(horizon_s, tau_s) >= 0.0
    ):
        return None  # NaN, inf, near it or a negative time: the reference's comparisons
    own_speed_m_s = math.hypot(vn_m_s, ve_m_s)
    cruise_m_s = g.cruise_speed_m_s
    speed_m_s = cruise_m_s if own_speed_m_s < cruise_m_s else own_speed_m_s  # np.maximum
    reach_m = speed_m_s * horizon_s  # travel = reach + BUFFER_M
    if _ARRIVING[mode] and not core.mission_waiting[0]:
        to_goal_m = math.hypot(tn_m - pn_m, te_m - pe_m)
        near = _below(
            to_goal_m,
            g.arrive_radius_m + (reach_m + BUFFER_M),
            to_goal_m + abs(g.arrive_radius_m) + reach_m + BUFFER_M,
        )
        if near is not False:
            return None if near is None else False
    fence_r = core.cfg.failsafe.geofence_radius_m
    if fence_r:
        from_home_m = math.hypot(pn_m, pe_m)
        inside = _below(
            from_home_m,
            fence_r - (reach_m + BUFFER_M),
            from_home_m + fence_r + reach_m + BUFFER_M,
        )
        if inside is not True:
            return inside
    if len(ext):
        clear = _neighbours_clear(
            s,
            ext,
            (pn_m, pe_m),
            (vn_m_s, ve_m_s),
            own_speed_m_s if mode == _HOLDING else speed_m_s,
            own_sigma_m,
            cruise_m_s,
            horizon_s,
        )
        if clear is not True:
            return clear
    router = core.router
    if router is not None:
        edge_m = float(router.edge_distance_m(obs.pos_m[:, :2])[0])
        clear_m = router.cfg.reach_m + s.sigma_k * own_sigma_m
        look_m = speed_m_s * (tau_s + horizon_s) + BUFFER_M
        return _below(clear_m + look_m, edge_m, abs(clear_m) + look_m)
    return True


def _neighbours_clear(
    s: SafetyConfig,
    ext: NeighbourSnapshot,
    pos_ne_m: tuple[float, float],
    vel_ne_m_s: tuple[float, float],
    own_bound_m_s: float,
    own_sigma_m: float,
    cruise_m_s: float,
    horizon_s: float,
) -> bool | None:
    """`calm_reference`'s neighbour rule for one vehicle, one neighbour at a time: False at the
    first whose closest approach (`closest_approach_m`) is surely within its calm distance, True
    when all are surely beyond theirs, None at the first too close to call. The vehicle's
    position, velocity, own bound (V_i) and position 1-sigma; finite, the times not negative."""
    pn_m, pe_m = pos_ne_m
    vn_m_s, ve_m_s = vel_ne_m_s
    k = len(ext)
    tau_s = s.time_horizon_s
    traffic_gain_m_s = TRAFFIC_ACCEL_M_S2 * horizon_s
    for (qn_m, qe_m, _), (un_m_s, ue_m_s, _), sigma_m, cooperative, manned in zip(
        ext.pos_ned_m.tolist(),
        ext.vel_ned_m_s.tolist(),
        _column_list(ext, "pos_sigma_m", 0.0, k),
        _column_list(ext, "cooperative", True, k),
        _column_list(ext, "manned", False, k),
        strict=True,
    ):
        closest_m = closest_approach_one_m(
            qn_m - pn_m, qe_m - pe_m, un_m_s - vn_m_s, ue_m_s - ve_m_s, tau_s
        )
        o_speed_m_s = math.hypot(un_m_s, ue_m_s)
        if cooperative:
            gain_m_s = 0.0
            o_bound_m_s = cruise_m_s if o_speed_m_s < cruise_m_s else o_speed_m_s  # NaN stays
        else:
            gain_m_s = traffic_gain_m_s
            o_bound_m_s = o_speed_m_s + gain_m_s
        gained_m = gain_m_s * tau_s
        flown_m = (own_bound_m_s + o_bound_m_s) * horizon_s
        r_m = pair_radius_one_m(s, own_sigma_m, sigma_m, cooperative, manned)
        near = _below(
            closest_m,
            r_m + gained_m + flown_m + BUFFER_M,
            closest_m + abs(r_m) + gained_m + flown_m + BUFFER_M,
        )
        if near is not False:
            return None if near is None else False
    return True


def _column_list(ext: NeighbourSnapshot, name: str, fill, k: int) -> list:
    """`ext.column(name, fill)` as a list of k Python values, without its array where it would
    only copy one: the column absent, or already k values of the fill's type."""
    got = getattr(ext, name)
    if got is None:
        return [fill] * k
    if isinstance(got, np.ndarray) and got.shape == (k,) and got.dtype is _DTYPES[type(fill)]:
        return got.tolist()
    return ext.column(name, fill).tolist()


def _below(a: float, b: float, scale: float) -> bool | None:
    """a < b (and a <= b: the same wherever it is told), None where it cannot be told from the
    reference's arrays: a and b within _TIE x `scale` (the size of the terms they are made of,
    non-negative) of each other, or either not finite."""
    gap = b - a
    slack = _TIE * scale
    if gap > slack:
        return True
    if gap < -slack:
        return False
    return None


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


def closest_approach_one_m(
    pn_m: float, pe_m: float, vn_m_s: float, ve_m_s: float, tau_s: float
) -> float:
    """`closest_approach_m` of one pair in plain floats, from its relative position (m) and
    velocity (m/s): the same operations, in the same order (math.hypot for np.hypot)."""
    vv = vn_m_s * vn_m_s + ve_m_s * ve_m_s
    t = min(max(-(pn_m * vn_m_s + pe_m * ve_m_s) / (vv if vv > 0.0 else 1.0), 0.0), tau_s)
    return math.hypot(pn_m + vn_m_s * t, pe_m + ve_m_s * t)
