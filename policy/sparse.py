"""The sparse-traffic rule: where a vehicle meets at most two others, and not dead-on, it flies
straight at its goal and leaves the encounter to the separation filter (policy.safety, ORCA);
everywhere else it flies the learned policy (issue 16, docs/policy.md "Sparse traffic").

Why: with exact states, ORCA resolves a lone crossing with the smallest change of velocity
(the later vehicle slows a little), while the policy turns early and wide. Two vehicles crossing
at 30-150 degrees, up to 3 m apart in time: policy 1.018 mean extra time (up to 1.10), ORCA
1.039 (up to 1.18: ORCA is at its worst dead-on, where both just slow down), this rule 1.006.
Dense, symmetric convergence (circles, forced conflicts) is where ORCA deadlocks and the
policy is needed; there a vehicle sees several encounters at once and keeps the policy.

At each decision, for one vehicle:
- v_s = straight at the goal at cruise speed, slower only to stop on it within one period;
- its encounters: neighbours whose closest approach over `horizon_periods` decision periods,
  own v_s against their reported velocity, comes nearer than `encounter_separations`; looked
  for only until v_s reaches the goal (the line ends there: what passes the goal later is the
  other vehicle's encounter, with a vehicle standing on its goal), unless the goal is taken
  (a neighbour within one separation of it now, `goal_taken`: then over the whole horizon,
  so that a vehicle on the goal, or pushed just past it, is dead-on and left to the policy);
- a covey neighbour slower than `still_speed_share` of the cruise speed stands (a vehicle
  holding its slot): one v_s passes outside the filter's berth for the pair is no encounter,
  one nearer is an encounter but never near now;
- it flies v_s when it has at most `max_encounters`, none closer than `dead_on_separations`,
  no neighbour nearer than `clear_separations` now unless it already flies along v_s, and
  the filter alone leaves v_s at least `progress_share` of its speed towards the goal; else
  the policy's velocity. Either is then held and filtered every tick as before.

firmware/covey_guidance.c covey_sparse_choose is its C twin (parity tested)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policy import safety


@dataclass(frozen=True)
class SparseConfig:
    """The rule's thresholds, in units of the separation and of the decision period."""

    horizon_periods: float = 10.0
    """How far ahead encounters are looked for (10 s at 3 m and 1 m/s), and never past the
    moment the straight line reaches the goal unless the goal is taken (`goal_taken`)."""
    encounter_separations: float = 2.0
    """A neighbour whose straight-line closest approach is nearer than this many separations
    is an encounter (6 m at 3 m)."""
    dead_on_separations: float = 1.0 / 6.0
    """An encounter nearer than this (0.5 m at 3 m) is dead-on: the policy flies it."""
    max_encounters: int = 2
    """More encounters than this at once is dense traffic: the policy flies it. Two, not one:
    large swarms 1.0035 -> 1.0018 (ORCA 1.0026; 1.0008 with the line ended at a free goal),
    for conflicts +0.4 % and circles +0.7 % (docs/policy.md "Two encounters at once")."""
    progress_share: float = 0.5
    """The filtered v_s must keep this share of its speed towards the goal (else the policy)."""
    clear_separations: float = 2.0
    """To take up the straight line, no neighbour may be nearer than this many separations now
    (6 m at 3 m), unless the vehicle already flies along it (`aligned_cos`): a vehicle the
    policy has turned aside next to a neighbour keeps the policy, which keeps its berth,
    rather than turning at the neighbour with only the filter, at its margin, on a stale link."""
    aligned_cos: float = 0.9
    """Flying along the straight line: the cosine between the own velocity and it (25 deg)."""
    still_speed_share: float = 0.25
    """A cooperative neighbour no faster than this share of the cruise speed is standing (a
    vehicle holding its slot or its goal). One the straight line passes no nearer than the
    filter's berth for the pair (policy.safety.pair_radius_m) is neither an encounter nor near:
    the filter would not act on it, and nothing reciprocal is left for the policy to resolve.
    One nearer is an encounter (dead-on still goes to the policy) but never near now
    (`clear_separations`): it will not turn into us, and the filter keeps its berth from a
    vehicle that stands. Without this, a vehicle bound for a formation slot between two
    holding vehicles 5 m either side was left to the policy, which circled the formation for
    minutes (docs/policy.md "Standing neighbours"). 0: nobody stands (the rule before)."""

    def __post_init__(self) -> None:
        for name in (
            "horizon_periods",
            "encounter_separations",
            "dead_on_separations",
            "clear_separations",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if not -1.0 <= self.aligned_cos <= 1.0:
            raise ValueError(f"aligned_cos must be within -1..1, got {self.aligned_cos}")
        if not 0.0 <= self.still_speed_share <= 1.0:
            raise ValueError(f"still_speed_share must be within 0..1, got {self.still_speed_share}")
        if not 0.0 <= self.progress_share <= 1.0:
            raise ValueError(f"progress_share must be within 0..1, got {self.progress_share}")
        if self.max_encounters < 0:
            raise ValueError(f"max_encounters must be >= 0, got {self.max_encounters}")


def straight_velocity(
    pos_m, goal_m, cruise_speed_m_s: float | np.ndarray, period_s: float
) -> np.ndarray:
    """(..., 2): at the goal at cruise speed (one, or one per row (...,)), slowed to reach it in
    one period when nearer."""
    d = np.asarray(goal_m, float) - np.asarray(pos_m, float)
    dist = np.hypot(d[..., 0], d[..., 1])
    # |v| = dist x gain = min(cruise, dist / period) exactly, down to 0 on the goal
    gain = np.minimum(cruise_speed_m_s / np.maximum(dist, 1e-9), 1.0 / max(period_s, 1e-9))
    return d * gain[..., None]


def time_to_goal_s(pos_m, goal_m, cruise_speed_m_s: float, period_s: float) -> np.ndarray:
    """(...,): how long `straight_velocity` takes to the goal, max(distance / cruise, period)
    (inside one period's reach it slows to arrive in exactly one period)."""
    d = np.asarray(goal_m, float) - np.asarray(pos_m, float)
    return np.maximum(np.hypot(d[..., 0], d[..., 1]) / cruise_speed_m_s, period_s)


def encounters(
    pos_m,
    v_straight,
    nbr_pos_m,
    nbr_vel_m_s,
    nbr_valid,
    horizon_s,
    radius_m,
    still_m_s: float = 0.0,
    berth_m=None,
):
    """(count (...,), nearest approach (...,), nearest now (...,)) in metres, inf when none: the
    neighbours (..., K, 2) whose closest approach to a vehicle flying v_straight, within
    horizon_s (a number, or (...,) per vehicle), is nearer than radius_m; and the nearest
    neighbour's distance now. With `berth_m` (..., K; inf: never standing), a neighbour no
    faster than `still_m_s` is standing: passed clear (closest approach at least its berth) it
    is left out of all three, else it is an encounter that is not near now
    (SparseConfig.still_speed_share)."""
    rp = np.asarray(nbr_pos_m, float) - np.asarray(pos_m, float)[..., None, :]
    nv = np.asarray(nbr_vel_m_s, float)
    rv = nv - np.asarray(v_straight, float)[..., None, :]
    vv = (rv * rv).sum(-1)
    t = np.minimum(
        np.maximum(-(rp * rv).sum(-1) / np.maximum(vv, 1e-12), 0.0),
        np.asarray(horizon_s, float)[..., None],
    )
    c = rp + rv * t[..., None]
    d = np.hypot(c[..., 0], c[..., 1])
    valid = np.asarray(nbr_valid, bool)
    moving = valid
    if berth_m is not None:
        standing = ((nv * nv).sum(-1) <= still_m_s * still_m_s) & np.isfinite(berth_m)
        valid = valid & ~(standing & (d >= berth_m))
        moving = valid & ~standing
    hit = (d < radius_m) & valid
    now = np.where(moving, np.hypot(rp[..., 0], rp[..., 1]), np.inf).min(-1, initial=np.inf)
    return hit.sum(-1), np.where(hit, d, np.inf).min(-1, initial=np.inf), now


def standing_berth_m(
    safety_cfg: safety.SafetyConfig,
    shape,
    pos_sigma_m=None,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    nbr_manned=None,
) -> np.ndarray:
    """(..., K) = `shape`: the berth past which a standing neighbour is passed clear, the
    filter's own for the pair (policy.safety.pair_radius_m); inf for traffic that does not
    cooperate (it may move off at any moment: it always counts)."""
    r, _ = safety.pair_radius_m(safety_cfg, pos_sigma_m, nbr_pos_sigma_m)
    berth = np.broadcast_to(np.asarray(r, float), shape)
    coop = safety.effective_cooperative(nbr_cooperative, nbr_manned)
    if coop is None:
        return berth
    return np.where(np.broadcast_to(np.asarray(coop, bool), shape), berth, np.inf)


def _standing_berths_one(
    safety_cfg: safety.SafetyConfig, cfg: SparseConfig, k: int, sky: dict
) -> list[float]:
    """`standing_berth_m` of one vehicle's k neighbours in Python floats (choose_one's hot
    path; equal to it bit for bit through safety.pair_radius_one_m); all inf when nobody
    stands (`still_speed_share` 0). `sky`: choose_one's."""
    if cfg.still_speed_share == 0.0:
        return [math.inf] * k
    own = sky.get("pos_sigma_m")
    sig, coop, manned = (sky.get(n) for n in ("nbr_pos_sigma_m", "nbr_cooperative", "nbr_manned"))
    if own is None and sig is None and coop is None and manned is None:
        return [safety_cfg.radius_m * (1.0 + safety_cfg.margin)] * k

    def column(x, fill, dtype) -> list:
        return [fill] * k if x is None else np.broadcast_to(np.asarray(x, dtype), (k,)).tolist()

    own_m = 0.0 if own is None else float(own)
    return [
        safety.pair_radius_one_m(safety_cfg, own_m, s, True, False) if c and not m else math.inf
        for s, c, m in zip(
            column(sig, 0.0, float),
            column(coop, True, bool),
            column(manned, False, bool),
            strict=True,
        )
    ]


def goal_taken(goal_m, nbr_pos_m, nbr_valid, sep_m: float) -> np.ndarray:
    """(...,): a neighbour (..., K, 2) is within one separation of the goal now. Whoever is
    there, standing or pushed aside, the encounters are then looked for over the whole horizon
    (a goto onto a holding vehicle's spot: tests/test_trust_keyed.py)."""
    d = np.asarray(nbr_pos_m, float) - np.asarray(goal_m, float)[..., None, :]
    return ((np.hypot(d[..., 0], d[..., 1]) < sep_m) & np.asarray(nbr_valid, bool)).any(-1)


def encounter_horizon_s(
    pos_m, goal_m, taken, cfg: SparseConfig, cruise_speed_m_s: float, period_s: float
):
    """(...,): how far ahead encounters are looked for: `horizon_periods`, cut at
    `time_to_goal_s` unless the goal is `taken`."""
    full = cfg.horizon_periods * period_s
    to_goal = time_to_goal_s(pos_m, goal_m, cruise_speed_m_s, period_s)
    return np.where(taken, full, np.minimum(full, to_goal))


def choose_padded(
    pos_m,
    vel_m_s,
    goal_m,
    v_policy,
    nbr_pos_m,
    nbr_vel_m_s,
    nbr_valid,
    safety_cfg: safety.SafetyConfig,
    cfg: SparseConfig,
    period_s: float,
    pos_sigma_m=None,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    nbr_manned=None,
):
    """The velocities to hold (N, 2) and which rows fly straight (N,), for N vehicles with
    padded views (N, K, ...) of their neighbours; safety_cfg is the filter flight keeps
    (its radius_m the separation, its max_speed_m_s the cruise speed). The uncertainties,
    cooperative and manned flags ((N,), (N, K), (N, K), (N, K) or None) go to the filter's
    progress check."""
    pos_m = np.asarray(pos_m, float)
    cruise = safety_cfg.max_speed_m_s
    v_s = straight_velocity(pos_m, goal_m, cruise, period_s)
    sep = safety_cfg.radius_m
    taken = goal_taken(goal_m, nbr_pos_m, nbr_valid, sep)
    valid = np.asarray(nbr_valid, bool)
    count, nearest, now = encounters(
        pos_m,
        v_s,
        nbr_pos_m,
        nbr_vel_m_s,
        valid,
        encounter_horizon_s(pos_m, goal_m, taken, cfg, cruise, period_s),
        cfg.encounter_separations * sep,
        cfg.still_speed_share * cruise,
        None
        if cfg.still_speed_share == 0.0
        else standing_berth_m(
            safety_cfg, valid.shape, pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned
        ),
    )
    vel_m_s = np.asarray(vel_m_s, float)
    along = (vel_m_s * v_s).sum(-1)
    aligned = along > 0.0
    aligned &= along * along >= cfg.aligned_cos**2 * (vel_m_s * vel_m_s).sum(-1) * (v_s * v_s).sum(
        -1
    )
    straight = (
        (count <= cfg.max_encounters)
        & (nearest >= cfg.dead_on_separations * sep)
        & ((now >= cfg.clear_separations * sep) | aligned)
    )
    rows = np.flatnonzero(straight)
    if rows.size:  # the filter only for the rows that may fly straight
        f = safety.filter_padded(
            pos_m[rows],
            vel_m_s[rows],
            v_s[rows],
            np.asarray(nbr_pos_m, float)[rows],
            np.asarray(nbr_vel_m_s, float)[rows],
            np.asarray(nbr_valid, bool)[rows],
            safety_cfg,
            pos_sigma_m=None if pos_sigma_m is None else np.asarray(pos_sigma_m)[rows],
            nbr_pos_sigma_m=None if nbr_pos_sigma_m is None else np.asarray(nbr_pos_sigma_m)[rows],
            nbr_cooperative=None if nbr_cooperative is None else np.asarray(nbr_cooperative)[rows],
            nbr_manned=None if nbr_manned is None else np.asarray(nbr_manned)[rows],
        )
        # (f . v_s / |v_s|) >= share |v_s|, without dividing: on the goal v_s = 0 passes
        s = v_s[rows]
        straight[rows] = (f * s).sum(-1) >= cfg.progress_share * (s * s).sum(-1)
    return np.where(straight[:, None], v_s, np.asarray(v_policy, float)), straight


def choose_one(
    pos_m,
    vel_m_s,
    goal_m,
    v_policy,
    nbr_pos_m,
    nbr_vel_m_s,
    safety_cfg: safety.SafetyConfig,
    cfg: SparseConfig,
    period_s: float,
    **sky,
) -> tuple[np.ndarray, bool]:
    """`choose_padded` for one vehicle and its k neighbours (k, 2): (velocity (2,), straight).
    In Python floats, with safety.filter_one: the runtime's hot path (equal to choose_padded,
    tests/test_policy_sparse.py). `sky`: safety.filter_one's pos_sigma_m, nbr_pos_sigma_m,
    nbr_cooperative, nbr_manned, for the progress check."""
    x, y = float(pos_m[0]), float(pos_m[1])
    gx, gy = float(goal_m[0]) - x, float(goal_m[1]) - y
    cruise = safety_cfg.max_speed_m_s
    gain = min(cruise / max(math.hypot(gx, gy), 1e-9), 1.0 / max(period_s, 1e-9))
    sx, sy = gx * gain, gy * gain
    sep = safety_cfg.radius_m
    radius_m = cfg.encounter_separations * sep
    nbr_pos = np.asarray(nbr_pos_m, float).reshape(-1, 2)
    nbr_vel = np.asarray(nbr_vel_m_s, float).reshape(-1, 2)
    pairs = list(zip(nbr_pos.tolist(), nbr_vel.tolist(), strict=True))
    # horizon_s: the line ends on the goal (time_to_goal_s) unless the goal is taken
    full_s = cfg.horizon_periods * period_s
    if any(math.hypot(nx - x - gx, ny - y - gy) < sep for (nx, ny), _ in pairs):
        horizon_s = full_s
    else:
        horizon_s = min(full_s, max(math.hypot(gx, gy) / cruise, period_s))
    count, nearest, now = 0, math.inf, math.inf
    still_m_s = cfg.still_speed_share * cruise
    berths = _standing_berths_one(safety_cfg, cfg, len(pairs), sky)
    for ((nx, ny), (nvx, nvy)), berth in zip(pairs, berths, strict=True):
        px, py = nx - x, ny - y
        rx, ry = nvx - sx, nvy - sy
        t = min(max(-(px * rx + py * ry) / max(rx * rx + ry * ry, 1e-12), 0.0), horizon_s)
        d = math.hypot(px + rx * t, py + ry * t)
        if berth == math.inf or nvx * nvx + nvy * nvy > still_m_s * still_m_s:
            now = min(now, math.hypot(px, py))
        elif d >= berth:
            continue  # a standing neighbour passed clear (SparseConfig.still_speed_share)
        if d < radius_m:
            count += 1
            nearest = min(nearest, d)
    vx, vy = float(vel_m_s[0]), float(vel_m_s[1])
    along = vx * sx + vy * sy
    v_s_sq = sx * sx + sy * sy
    aligned = along > 0.0 and along * along >= cfg.aligned_cos**2 * (vx * vx + vy * vy) * v_s_sq
    straight = (
        count <= cfg.max_encounters
        and nearest >= cfg.dead_on_separations * sep
        and (now >= cfg.clear_separations * sep or aligned)
    )
    v_s = np.array((sx, sy))
    if straight and len(nbr_pos):
        f = safety.filter_one((x, y), (vx, vy), v_s, nbr_pos, nbr_vel, safety_cfg, **sky)
        straight = float(f[0] * sx + f[1] * sy) >= cfg.progress_share * v_s_sq
    return (v_s if straight else np.asarray(v_policy, float).reshape(2)), bool(straight)
