"""Closed-loop evaluation simulator with an emulated broadcast link.

Point masses fly the commanded velocity (Euler, dt_s); heading is the direction of
the last displacement, at the start the goal. Each vehicle knows itself exactly
and the others only through what the link delivered: broadcasts at `rate_hz`
(random phase), each copy lost with probability `loss`, delivered `latency_s`
later. Vehicles fly through policy.pointmass's `VehicleModel` (`EvalSimConfig.vehicles`): with
the ideal one they fly the command exactly and know where they are; with a realistic one the
controllers see (and the link carries) each vehicle's drifting position estimate and its
ground velocity, with the 1-sigma it reports, while collisions and the closest approach are
judged on the true positions (`min_sep`, `collisions`; on the estimates: `est_min_sep`,
`est_collisions`). Like the agents' neighbour tables (agent/neighbours.py), a receiver dead-reckons the last
state it got to now at that state's velocity, from when it got it (`dead_reckon`). Vehicles leave on arrival and on collision (as in training); a departed
vehicle is known to have left (presence tokens), so it is no longer avoided.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from comms.link import PROFILES, LinkProfile
from policy.pointmass import VehicleModel, Vehicles
from policy.sparse import straight_velocity
from policy.tracking import Tracking, TrackingConfig


@dataclass(frozen=True)
class LinkConfig:
    """Neighbour-state link; the defaults are a perfect link."""

    rate_hz: float = 0.0
    """Broadcast rate; 0 = every step, no loss or latency (perfect)."""
    loss: float = 0.0
    """Probability that one receiver misses one broadcast."""
    latency_s: float = 0.0
    """Delay from broadcast to delivery."""

    @property
    def perfect(self) -> bool:
        return self.rate_hz <= 0

    @classmethod
    def of(cls, profile: LinkProfile) -> LinkConfig:
        """The evaluation link for one of the mesh's link profiles (comms/link.py, the one
        table): its rate, Bernoulli loss and latency; jitter and range are not modelled here."""
        if profile.ge is not None or profile.range_m:
            raise ValueError(
                f"link profile {profile.name!r}: the evaluation link takes rate, loss and latency only"
            )
        return cls(rate_hz=profile.rate_hz or 0.0, loss=profile.loss, latency_s=profile.latency_s)


PERFECT = LinkConfig.of(PROFILES["perfect"])
DEGRADED = LinkConfig.of(PROFILES["xbee"])
"""The paper's XBee link (3 Hz) with 20 % loss and 100 ms latency."""


@dataclass(frozen=True)
class EvalSimConfig:
    """Closed-loop evaluation settings (policy units: 3 m separation, 1 m/s)."""

    dt_s: float = 0.1
    """Control and integration step."""
    speed: float = 1.0
    """Cruise speed (the straight-line time is distance / speed)."""
    arrive_m: float = 1.0
    """Arrival radius."""
    collide_m: float = 3.0
    """A pair closer than this collides."""
    time_factor: float = 4.0
    """A vehicle times out after time_factor x its straight-line time."""
    record: bool = False
    """Keep the trajectories (for plots)."""
    vehicles: VehicleModel = VehicleModel()
    """How the vehicles fly and how well they know where they are (VehicleModel.ideal() or
    .realistic()); arrival is judged on the estimate (what the vehicle knows), collisions on
    the truth."""
    tracking: TrackingConfig | None = None
    """The tracking compensation of the covey vehicles' commands (policy/tracking.py), as the
    agents fly it; None: on, with the vehicles' own loop (`TrackingConfig.for_model`);
    `TrackingConfig(enabled=False)`: off. Intruders are never corrected."""
    manned_berth_m: float = 30.0
    """A covey vehicle closer than this to a manned aircraft (a `manned` intruder) entered its
    berth (`manned_entries`; policy.safety's MANNED_SEPARATION_M, before margin and
    uncertainty)."""
    dead_reckon: bool = True
    """Receivers extrapolate each neighbour's last delivered state to now, p + v (t - t_rx), as
    the agents do (agent/neighbours.py); False: they use it as it came (staler on a slow link)."""


# controller(ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid) -> vel (N, 2)
# ids are the vehicle numbers of the rows (the active vehicles), t_s the time. A controller
# with `uses_sigma = True` also gets pos_sigma_m= (N,) and nbr_pos_sigma_m= (N, K): the
# position 1-sigma each vehicle reports of itself and the ones its link delivered; with
# `uses_cooperative = True`, nbr_cooperative= (N, K) bool when the case has traffic that does
# not cooperate (False for those columns; a controller without it takes them for covey vehicles)
# and, when some of them are manned aircraft, nbr_manned= (N, K) bool (True for those columns).
Controller = Callable[..., np.ndarray]


def straight_line(ids, t_s, pos, vel, heading, goal, *_):
    """Baseline: fly straight at the goal at unit speed (slower within 1 m: stop on it in 1 s),
    the line the sparse rule flies (policy.sparse.straight_velocity)."""
    return straight_velocity(pos, goal, 1.0, 1.0)


def run(
    starts,
    goals,
    controller: Controller,
    link: LinkConfig,
    cfg: EvalSimConfig,
    rng: np.random.Generator,
    non_cooperative=None,
    speed_m_s=None,
    manned=None,
    flying_start: bool = False,
) -> dict:
    """Flies one scenario to the end; returns its metrics (and tracks if cfg.record).
    `non_cooperative` (n,) bool marks intruders: they fly straight at their goal at their
    `speed_m_s` (n,) whatever happens (the controller never steers them), broadcast like the
    others, and are told to controllers as not cooperating. `manned` (n,) bool marks the
    intruders that are manned aircraft (told as nbr_manned; `manned_min_sep` and
    `manned_entries`, the covey vehicles that came within cfg.manned_berth_m of one). Success,
    arrivals, timeouts, times and paths count the covey vehicles only; a covey vehicle that hits
    an intruder collided. `flying_start`: every vehicle is already flying its straight line at
    its speed when the scene starts (else the covey vehicles and unmanned intruders start at
    rest: a realistic vehicle takes a moment to reach its speed)."""
    starts = np.asarray(starts, dtype=np.float64)
    goals = np.asarray(goals, dtype=np.float64)
    n = starts.shape[0]
    nc = np.zeros(n, bool) if non_cooperative is None else np.asarray(non_cooperative, bool)
    mn = np.zeros(n, bool) if manned is None else np.asarray(manned, bool)
    if (mn & ~nc).any():
        raise ValueError("a manned aircraft must be one of the non_cooperative vehicles")
    own_speed = np.full(n, cfg.speed) if speed_m_s is None else np.asarray(speed_m_s, float)
    uses_coop = nc.any() and bool(getattr(controller, "uses_cooperative", False))
    # a manned aircraft is already flying when the scene starts (at the realistic 2.5 m/s^2 a
    # 60 m/s one would take 24 s to speed up, and pass late); everyone else starts at rest
    vel0 = np.zeros_like(starts)
    moving = np.ones(n, bool) if flying_start else mn
    if moving.any():
        vel0[moving] = straight_velocity(starts[moving], goals[moving], own_speed[moving], cfg.dt_s)
    fleet = Vehicles(starts, cfg.vehicles, rng, vel0)
    pos = fleet.pos_m  # the truth, flown in place
    est, gvel = fleet.est_pos_m, fleet.ground_vel_m_s
    sigma = np.full(n, fleet.pos_sigma_m)
    uses_sigma = bool(getattr(controller, "uses_sigma", False))
    rel = goals - starts
    trip = np.hypot(rel[:, 0], rel[:, 1])
    heading = np.arctan2(rel[:, 1], rel[:, 0])
    active = np.ones(n, bool)
    arrive_t = np.full(n, np.nan)
    collided = np.zeros(n, bool)
    est_collided = np.zeros(n, bool)
    timed_out = np.zeros(n, bool)
    path = np.zeros(n)
    acc_sum, acc_n = 0.0, 0
    min_sep = est_min_sep = intruder_min_sep = manned_min_sep = np.inf
    in_berth = np.zeros(n, bool)  # covey vehicles that came within the manned berth
    t_limit = cfg.time_factor * trip / own_speed
    # what receiver i last got from sender j
    k_pos, k_vel, k_head = (
        np.broadcast_to(est, (n, n, 2)).copy(),
        np.zeros((n, n, 2)),
        np.broadcast_to(heading, (n, n)).copy(),
    )
    k_sig = np.broadcast_to(sigma, (n, n)).copy()
    k_rx = np.zeros((n, n))  # when receiver i got sender j's state
    first_rx = np.zeros((n, n)) if link.perfect else np.full((n, n), np.nan)  # ... the first
    phase = rng.uniform(0, 1.0 / link.rate_hz, n) if not link.perfect else np.zeros(n)
    next_tx = phase.copy()
    pending: list = []  # (deliver_at, sender, receivers mask, pos, vel, heading, sigma)
    eye = np.eye(n, dtype=bool)
    tracks = [pos.copy()] if cfg.record else None
    track = Tracking(
        cfg.tracking if cfg.tracking is not None else TrackingConfig.for_model(cfg.vehicles), n
    )
    t = 0.0
    steps = 0
    while active.any():
        if link.perfect:
            nbr_pos, nbr_vel, nbr_head = (
                np.broadcast_to(a, (n, *a.shape)) for a in (est, gvel, heading)
            )
            nbr_sig = np.broadcast_to(sigma, (n, n))
        else:
            # broadcasts due now, then deliveries due now
            for j in np.flatnonzero(active & (next_tx <= t + 1e-9)):
                recv = rng.random(n) >= link.loss
                pending.append(
                    (
                        t + link.latency_s,
                        j,
                        recv,
                        est[j].copy(),
                        gvel[j].copy(),
                        heading[j],
                        sigma[j],
                    )
                )
                next_tx[j] += 1.0 / link.rate_hz
            keep = []
            for msg in pending:
                if msg[0] <= t + 1e-9:
                    _, j, recv, p, v, h, sg = msg
                    k_pos[recv, j], k_vel[recv, j], k_head[recv, j] = p, v, h
                    k_sig[recv, j] = sg
                    k_rx[recv, j] = t
                    first_rx[recv, j] = np.where(np.isnan(first_rx[recv, j]), t, first_rx[recv, j])
                else:
                    keep.append(msg)
            pending = keep
            nbr_pos, nbr_vel, nbr_head, nbr_sig = k_pos, k_vel, k_head, k_sig
            if cfg.dead_reckon:
                nbr_pos = k_pos + k_vel * (t - k_rx)[..., None]
        valid = active[None, :] & active[:, None] & ~eye
        idx = np.flatnonzero(active)
        ctl = idx[~nc[idx]]  # the covey vehicles: intruders are never steered
        v = np.zeros((n, 2))
        extra = {}
        if uses_sigma:
            extra = {"pos_sigma_m": sigma[ctl], "nbr_pos_sigma_m": nbr_sig[ctl]}
        if uses_coop:
            extra["nbr_cooperative"] = np.broadcast_to(~nc, (ctl.size, n))
            if mn.any():
                extra["nbr_manned"] = np.broadcast_to(mn, (ctl.size, n))
        if ctl.size:
            v[ctl] = controller(
                ctl,
                t,
                est[ctl],
                gvel[ctl],
                heading[ctl],
                goals[ctl],
                nbr_pos[ctl],
                nbr_vel[ctl],
                nbr_head[ctl],
                valid[ctl],
                **extra,
            )
            v[ctl] = track.correct(ctl, t, v[ctl], gvel[ctl])
        straight = idx[nc[idx]]
        for i in straight:  # each at its own speed, on the truth (it knows where it goes)
            v[i] = straight_velocity(pos[i], goals[i], float(own_speed[i]), cfg.dt_s)
        acc = np.hypot(*(v[ctl] - gvel[ctl]).T) / cfg.dt_s  # the covey vehicles'
        acc_sum += float(acc.sum())
        acc_n += ctl.size
        before = pos.copy()
        # the point mass flies the command (exactly, with ideal vehicles), only active ones
        powered = active.copy()
        fleet.step(v, cfg.dt_s, powered)
        pos[~active] = before[~active]
        est, gvel = fleet.est_pos_m, fleet.ground_vel_m_s
        disp = pos - before
        step_len = np.hypot(disp[:, 0], disp[:, 1])
        flown = fleet.vel_m_s * cfg.dt_s  # heading: where the loop flies, not where gusts push
        flown_len = np.hypot(flown[:, 0], flown[:, 1])
        heading = np.where(flown_len > 1e-9, np.arctan2(flown[:, 1], flown[:, 0]), heading)
        path += step_len
        t += cfg.dt_s
        steps += 1
        if tracks is not None:
            tracks.append(np.where(active[:, None], pos, np.nan))
        # separation among the vehicles that flew this step: true positions, and estimates
        if idx.size > 1:
            d = _pair_dist(pos[idx])
            min_sep = min(min_sep, float(d.min()))
            de = d if cfg.vehicles.drift_m == 0 else _pair_dist(est[idx])
            est_min_sep = min(est_min_sep, float(de.min()))
            hit = (d < cfg.collide_m).any(axis=1)
            if nc.any():  # covey vehicle to intruder, true positions
                m = nc[idx]
                if m.any() and (~m).any():
                    intruder_min_sep = min(intruder_min_sep, float(d[~m][:, m].min()))
                    a = mn[idx]
                    if a.any():
                        to_manned = d[~m][:, a].min(axis=1)
                        manned_min_sep = min(manned_min_sep, float(to_manned.min()))
                        in_berth[idx[~m][to_manned < cfg.manned_berth_m]] = True
            est_collided[idx[(de < cfg.collide_m).any(axis=1)]] = True
        else:
            hit = np.zeros(idx.size, bool)
        collided[idx[hit]] = True
        gd = goals[idx] - est[idx]
        arrived = (np.hypot(gd[:, 0], gd[:, 1]) <= cfg.arrive_m) & ~hit
        arrive_t[idx[arrived]] = t
        late = (t >= t_limit[idx]) & ~arrived & ~hit
        timed_out[idx[late]] = True
        active[idx[hit | arrived | late]] = False
    ok = ~np.isnan(arrive_t) & ~nc
    coop = ~nc
    out: dict[str, Any] = {
        "n": int(coop.sum()),
        "success": bool(ok.sum() == coop.sum() and not collided[coop].any()),
        "arrived": int(ok.sum()),
        "collisions": int(collided[coop].sum()),
        "timeouts": int(timed_out[coop].sum()),
        "min_sep": float(min_sep) if np.isfinite(min_sep) else None,
        "est_collisions": int(est_collided[coop].sum()),
        "est_min_sep": float(est_min_sep) if np.isfinite(est_min_sep) else None,
        "intruder_min_sep": float(intruder_min_sep) if np.isfinite(intruder_min_sep) else None,
        "manned_min_sep": float(manned_min_sep) if np.isfinite(manned_min_sep) else None,
        "manned_entries": int(in_berth[coop].sum()),
        "intruder_heard_s": _heard_s(first_rx, coop, nc),
        "extra_time": float(np.mean(arrive_t[ok] * cfg.speed / trip[ok])) if ok.any() else None,
        "path_ratio": float(np.mean(path[ok] / trip[ok])) if ok.any() else None,
        "mean_acc": acc_sum / max(acc_n, 1),
        "steps": steps,
    }
    if tracks is not None:
        out["tracks"] = np.array(tracks)
        out["goals"] = goals
    return out


def _heard_s(first_rx: np.ndarray, coop: np.ndarray, nc: np.ndarray) -> float | None:
    """When the last covey vehicle first heard an intruder (the latest first reception over the
    pairs; 0 on a perfect link); None without intruders, or where one was never heard (a
    number only when every covey vehicle heard every intruder: results are written as JSON)."""
    if not (nc.any() and coop.any()):
        return None
    got = first_rx[np.ix_(coop, nc)]
    return None if np.isnan(got).any() else float(got.max())


def _pair_dist(p: np.ndarray) -> np.ndarray:
    """Distances between the rows of p (M, 2), the diagonal 1e9."""
    dx = p[:, None, :] - p[None, :, :]
    return np.hypot(dx[..., 0], dx[..., 1]) + np.eye(p.shape[0]) * 1e9
