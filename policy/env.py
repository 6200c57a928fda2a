"""Vectorised training environment: E arenas padded to M vehicles, with masks.

Point masses in the plane (x north, y east, policy units), Euler steps of dt = 1 s,
velocity command = the unit-clipped body-frame action rotated by the heading.
Heading is the direction of the last displacement (at the start: the goal).
Vehicles leave on arrival, on collision and at the step limit. Rewards follow the
paper (PAPER.md): w_cav R_CAV + w_acc R_ACC + w_tme R_TME + w_arr R_ARR.
`reference_step` is a plain per-agent loop that `SwarmEnv.step` must equal.

Flight's conditions on request (issue 35, "trained with noisy positions"): `drift_m` gives each
vehicle a drifting position estimate (the one Gauss-Markov process of policy.pointmass), which
is all the network, the filter (inflated by sigma_k x the pair's combined sigma) and the
arrival see, while collisions and the proximity penalty are judged on the truth; `told_scale`
zooms the network's view as flight's told separation does (units are then metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policy import features, safety
from policy.features import ObsConfig
from policy.pointmass import gauss_markov, integrate


@dataclass(frozen=True)
class EnvConfig:
    """Arena, episode and reward constants (the code's values by default)."""

    num_envs: int = 64
    """E, arenas simulated side by side."""
    max_vehicles: int = 5
    """M, the cap of the vehicle count and the padding size."""
    p_vehicles: float = 1.0 / 3.0
    """Vehicle count n ~ geometric(p), P(n) = (1-p)^(n-1) p, capped at max_vehicles."""
    arena_m: float = 60.0
    """Side of the square arena holding starts and goals."""
    min_gap_m: float = 10.0
    """Starts apart from starts, goals from goals, and each goal from its start."""
    dt_s: float = 1.0
    """Euler step."""
    max_steps: int = 100
    """Steps before the remaining vehicles time out."""
    speed: float = 1.0
    """Speed of a unit action."""
    eps_arr_m: float = 1.0
    """Arrival radius."""
    eps_cav_m: float = 3.0
    """Collision distance (the separation)."""
    knee_cav_m: float = 6.0
    """R_CAV is linear from 0 at delta_cav_m to -2 here, then quadratic to -1000 at eps_cav_m."""
    delta_cav_m: float = 10.0
    """R_CAV is zero beyond this."""
    r_arr: float = 1000.0
    """Arrival reward."""
    r_col: float = 1000.0
    """Collision penalty (per neighbour inside eps_cav_m)."""
    r_tme: float = 100.0
    """Time penalty per step is r_tme / trip length."""
    w_cav: float = 1.0
    """Weight of R_CAV."""
    w_acc: float = 6.0
    """Weight of R_ACC = -|lateral action|."""
    w_tme: float = 1.5
    """Weight of R_TME."""
    w_arr: float = 1.0
    """Weight of R_ARR."""
    ccd: bool = False
    """Check collisions along each step (closest approach of the two straight segments),
    not only at its end. With dt = 1 s and closing speeds up to 2 m/s, end-of-step
    checks miss pairs that pass through each other; the paper checks at the end."""
    w_prog: float = 0.0
    """Weight of a progress term (metres gained towards the goal this step); 0 in the
    paper. It is potential-based shaping (Phi = -distance), so it does not change
    the optimal policy, but it makes the first arrivals far easier to discover."""
    conflict_share: float = 0.0
    """Share of arenas drawn as forced conflicts (`sample_conflict`: starts on a circle, goals
    near the opposite side, every path through the middle) instead of uniformly in the
    arena; 0 in the paper. Uniform arenas rarely hold the dense, symmetric encounters in
    which a policy that leans on the filter deadlocks."""
    safety_filter: bool = False
    """Fly every commanded velocity through the separation filter (policy.safety, ORCA), as
    flight does, with each vehicle seeing the others of its arena exactly: the policy then
    learns with the guarantee it will fly with (issue 16). Off in the paper."""
    filter_margin: float = safety.SafetyConfig.margin
    """That filter's relative padding on eps_cav_m (flight's SafetyConfig.margin by default)."""
    drift_m: float = 0.0
    """Each vehicle's position estimate drifts from the truth: 1-sigma per axis of a
    Gauss-Markov offset (policy.pointmass.VehicleModel.drift_m; 0.5 for plain GNSS in metres).
    The network, the filter and the arrival see the estimates; collisions and R_CAV the truth.
    0: the estimates are the truth (the paper, and every stage of the shipped weights)."""
    drift_corr_s: float = 10.0
    """Correlation time of that drift."""
    sigma_k: float = safety.SIGMA_K
    """With drift_m and the filter: the filter keeps sigma_k sqrt(2) drift_m more between
    estimates, as flight's does (SafetyConfig.sigma_k)."""
    told_scale: float = 1.0
    """The network sees positions and goals times this: flight tells weights their
    `filtered_told_share` of the separation (policy.runtime), so in an arena in metres a
    network told 1.25 m per 3 m sees the world 3 / 1.25 = 2.4 times larger. 1: it sees the
    arena's own units (every stage of the shipped weights; the last, in metres on drifting
    estimates, is told the whole separation)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.filter_margin <= 10.0:
            raise ValueError(f"filter_margin must be in [0, 10], got {self.filter_margin}")
        for name in ("drift_m", "sigma_k"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        for name in ("drift_corr_s", "told_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")


def cav_reward(d, cfg: EnvConfig):
    """R_CAV of one pair at distance d (vectorised)."""
    d = np.asarray(d, dtype=np.float64)
    lin = -2.0 * (cfg.delta_cav_m - d) / (cfg.delta_cav_m - cfg.knee_cav_m)
    quad = -2.0 - (cfg.r_col - 2.0) * ((cfg.knee_cav_m - d) / (cfg.knee_cav_m - cfg.eps_cav_m)) ** 2
    out = np.where(d >= cfg.delta_cav_m, 0.0, np.where(d >= cfg.knee_cav_m, lin, quad))
    return np.where(d <= cfg.eps_cav_m, -cfg.r_col, out)


def safety_config(cfg: EnvConfig) -> safety.SafetyConfig:
    """The filter of `safety_filter` in policy units: it keeps the collision distance at the
    vehicles' speed with `filter_margin` (its other settings are flight's)."""
    return safety.SafetyConfig(
        radius_m=cfg.eps_cav_m,
        margin=cfg.filter_margin,
        dt_s=cfg.dt_s,
        max_speed_m_s=cfg.speed,
        sigma_k=cfg.sigma_k,
    )


def sample_vehicle_count(rng: np.random.Generator, cfg: EnvConfig) -> int:
    return int(min(rng.geometric(cfg.p_vehicles), cfg.max_vehicles))


def sample_scenario(rng: np.random.Generator, n: int, cfg: EnvConfig):
    """Starts and goals (n, 2) in the arena, min_gap_m apart (rejection sampling)."""
    starts: list = []
    goals: list = []
    for _ in range(n):
        for _ in range(10000):
            s = rng.uniform(0.0, cfg.arena_m, 2)
            if all(np.hypot(*(s - o)) >= cfg.min_gap_m for o in starts):
                break
        for _ in range(10000):
            g = rng.uniform(0.0, cfg.arena_m, 2)
            if np.hypot(*(g - s)) >= cfg.min_gap_m and all(
                np.hypot(*(g - o)) >= cfg.min_gap_m for o in goals
            ):
                break
        starts.append(s)
        goals.append(g)
    return np.array(starts).reshape(n, 2), np.array(goals).reshape(n, 2)


def sample_conflict(rng: np.random.Generator, n: int, cfg: EnvConfig):
    """Starts (n, 2) on a circle about the arena's centre (radius 12-28 m, 6 m apart at least)
    and goals at the opposite points moved by up to 0-4 m (kept 6 m apart): every straight
    path crosses near the centre, from exactly antipodal to loosely so."""
    centre = np.full(2, cfg.arena_m / 2)
    radius_m = rng.uniform(12.0, 28.0)
    jitter_m = rng.uniform(0.0, 4.0)
    placed: list = []
    for _ in range(n):
        for _ in range(10000):
            a = rng.uniform(0.0, 2 * np.pi)
            p = radius_m * np.array([np.cos(a), np.sin(a)])
            if all(np.hypot(*(p - o)) >= 6.0 for o in placed):
                break
        placed.append(p)
    starts = np.array(placed).reshape(n, 2)
    goals = -starts  # as far apart as the starts; each moves only where it stays 6 m clear
    for i in range(n):
        g = goals[i] + rng.uniform(-jitter_m, jitter_m, 2)
        if all(np.hypot(*(g - goals[j])) >= 6.0 for j in range(n) if j != i):
            goals[i] = g
    return starts + centre, goals + centre


class SwarmEnv:
    """E arenas of up to M vehicles; arrays are (E, M, ...) with an `active` mask."""

    def __init__(self, cfg: EnvConfig, obs_cfg: ObsConfig):
        self.cfg = cfg
        self.obs_cfg = obs_cfg
        e, m = cfg.num_envs, cfg.max_vehicles
        self.pos = np.zeros((e, m, 2))
        self.goal = np.zeros((e, m, 2))
        self.heading = np.zeros((e, m))
        self.vel = np.zeros((e, m, 2))
        """Velocity flown in the last step (what the filter sees of each vehicle)."""
        self.active = np.zeros((e, m), dtype=bool)
        self.trip_m = np.ones((e, m))
        self.t = np.zeros(e, dtype=np.int64)
        self.ep_return = np.zeros((e, m))
        self.ep_arrived = np.zeros((e, m), dtype=bool)
        self.ep_collided = np.zeros((e, m), dtype=bool)
        self.drift = np.zeros((e, m, 2))
        """Estimate minus truth of each vehicle's position (0 without cfg.drift_m)."""
        self.rng = np.random.default_rng(0)

    @property
    def est(self) -> np.ndarray:
        """What each vehicle believes its position is (E, M, 2): the truth plus its drift."""
        return self.pos + self.drift

    def reset(self, seed: int | None = None):
        """Resets every arena; returns the observation."""
        self.rng = np.random.default_rng(seed)
        self.reset_envs(np.ones(self.cfg.num_envs, dtype=bool))
        return self.observe()

    def reset_envs(self, mask) -> None:
        """Draws new scenarios for the arenas in mask."""
        for e in np.flatnonzero(mask):
            if self.cfg.conflict_share > 0 and self.rng.random() < self.cfg.conflict_share:
                n = int(self.rng.integers(2, self.cfg.max_vehicles + 1))
                s, g = sample_conflict(self.rng, n, self.cfg)
            else:
                n = sample_vehicle_count(self.rng, self.cfg)
                s, g = sample_scenario(self.rng, n, self.cfg)
            self.pos[e] = 0.0
            self.vel[e] = 0.0
            self.goal[e] = 0.0
            self.pos[e, :n] = s
            self.goal[e, :n] = g
            self.drift[e] = 0.0
            if self.cfg.drift_m > 0:  # stationary from the start; no draw when off
                self.drift[e, :n] = self.rng.standard_normal((n, 2)) * self.cfg.drift_m
            self.active[e] = False
            self.active[e, :n] = True
            rel = self.goal[e] - self.pos[e]
            self.heading[e] = np.arctan2(rel[:, 1], rel[:, 0])
            self.trip_m[e] = np.maximum(np.hypot(rel[:, 0], rel[:, 1]), 1e-6)
            self.t[e] = 0
            self.ep_return[e] = 0.0
            self.ep_arrived[e] = False
            self.ep_collided[e] = False

    def observe(self, max_neighbours=None):
        """(seq (E,M,K,X), lengths (E,M), goal features (E,M,G))."""
        zoom = self.cfg.told_scale
        seq, lengths, goal_feat, _ = features.observe_batch(
            self.est * zoom,
            self.heading,
            self.goal * zoom,
            self.active,
            self.obs_cfg,
            max_neighbours,
        )
        return seq, lengths, goal_feat

    def step(self, actions):
        """Advances all arenas by one step.

        actions (E, M, 2) body frame (clipped here to unit length). Returns
        (reward (E,M), done (E,M), info). done marks vehicles that left this step;
        info["env_done"] (E,) marks arenas with no vehicle left (call reset_envs).
        """
        cfg = self.cfg
        act = self.active.copy()
        gd0 = self.goal - self.est
        a = features.clip_unit(actions)
        vel = features.action_to_velocity(a, self.heading) * cfg.speed * act[..., None]
        if cfg.safety_filter:
            vel = self._filtered(vel, act)
        self.vel = vel
        disp = vel * cfg.dt_s
        pos = self.pos.copy()  # the one point-mass model, every arena's vehicles as rows
        integrate(pos.reshape(-1, 2), np.zeros((pos.size // 2, 2)), vel.reshape(-1, 2), cfg.dt_s)
        self.pos = pos
        moved = act & (np.hypot(disp[..., 0], disp[..., 1]) > 1e-12)
        self.heading = np.where(moved, np.arctan2(disp[..., 1], disp[..., 0]), self.heading)
        rel = self.pos[:, None, :, :] - self.pos[:, :, None, :]
        d = np.hypot(rel[..., 0], rel[..., 1])
        m = cfg.max_vehicles
        pair = act[:, :, None] & act[:, None, :] & ~np.eye(m, dtype=bool)
        r_cav = np.where(pair, cav_reward(d, cfg), 0.0).sum(-1)
        if cfg.ccd:
            d = np.minimum(
                d, _closest_approach(rel - (disp[:, None, :, :] - disp[:, :, None, :]), rel)
            )
        collided = (pair & (d <= cfg.eps_cav_m)).any(-1)
        gauss_markov(self.drift, cfg.drift_m, cfg.drift_corr_s, cfg.dt_s, self.rng)
        gd = self.goal - self.est
        arrived = act & (np.hypot(gd[..., 0], gd[..., 1]) <= cfg.eps_arr_m)
        r_arr = cfg.r_arr * arrived
        r_tme = -cfg.r_tme / self.trip_m
        r_acc = -np.abs(a[..., 1])
        r_prog = np.hypot(gd0[..., 0], gd0[..., 1]) - np.hypot(gd[..., 0], gd[..., 1])
        reward = (
            cfg.w_cav * r_cav
            + cfg.w_acc * r_acc
            + cfg.w_tme * r_tme
            + cfg.w_arr * r_arr
            + cfg.w_prog * r_prog
        ) * act
        self.t = self.t + 1
        timeout = act & (self.t >= cfg.max_steps)[:, None]
        done = act & (arrived | collided | timeout)
        self.active = act & ~done
        self.ep_return += reward
        self.ep_arrived |= arrived & ~collided
        self.ep_collided |= act & collided
        env_done = ~self.active.any(axis=1)
        info = {
            "arrived": arrived & ~collided,
            "collided": act & collided,
            "timeout": timeout & ~arrived & ~collided,
            "env_done": env_done,
        }
        return reward, done, info

    def _filtered(self, vel, act):
        """vel (E, M, 2) through the separation filter; each active vehicle sees the other
        active vehicles of its arena (their estimated positions, with the drift's sigma, and
        last velocities)."""
        m = self.cfg.max_vehicles
        e_i, m_i = np.nonzero(act)
        if e_i.size == 0:
            return vel
        valid = act[e_i] & (np.arange(m)[None, :] != m_i[:, None])
        out = vel.copy()
        est = self.est
        sigma = {}
        if self.cfg.drift_m > 0:
            sigma = {
                "pos_sigma_m": np.full(e_i.size, self.cfg.drift_m),
                "nbr_pos_sigma_m": np.full(valid.shape, self.cfg.drift_m),
            }
        out[e_i, m_i] = safety.filter_padded(
            est[e_i, m_i],
            self.vel[e_i, m_i],
            vel[e_i, m_i],
            est[e_i],
            self.vel[e_i],
            valid,
            safety_config(self.cfg),
            **sigma,
        )
        return out

    def episode_stats(self, mask):
        """Per finished arena: (mean vehicle return, all arrived, any collision)."""
        out = []
        for e in np.flatnonzero(mask):
            n = int((self.trip_m[e] > 1e-6).sum())
            n = max(n, 1)
            out.append(
                (
                    float(self.ep_return[e, :n].mean()),
                    bool(self.ep_arrived[e, :n].all()),
                    bool(self.ep_collided[e, :n].any()),
                )
            )
        return out


def _closest_approach(rel0, rel1):
    """min over s in [0, 1] of |rel0 + s (rel1 - rel0)| (vectorised over pairs)."""
    b = rel1 - rel0
    bb = (b * b).sum(-1)
    s = np.clip(-(rel0 * b).sum(-1) / np.maximum(bb, 1e-12), 0.0, 1.0)
    p = rel0 + s[..., None] * b
    return np.hypot(p[..., 0], p[..., 1])


def reference_step(
    pos,
    goal,
    heading,
    active,
    trip_m,
    t,
    actions,
    cfg: EnvConfig,
    vel=None,
    drift=None,
    drift_after=None,
):
    """Plain per-agent loop of SwarmEnv.step on copies; returns the same quantities.
    `vel` (E, M, 2): the velocities flown in the last step (needed with cfg.safety_filter).
    `drift` / `drift_after` (E, M, 2): the estimates' drift before and after the step (the
    env's draws; None: 0), which the filter, the progress and the arrival see."""
    e_n, m = active.shape
    drift = np.zeros_like(pos) if drift is None else drift
    drift_after = np.zeros_like(pos) if drift_after is None else drift_after
    pos0 = pos
    pos, heading, active = pos.copy(), heading.copy(), active.copy()
    if cfg.safety_filter:
        if vel is None:
            raise ValueError("reference_step with safety_filter needs vel")
        new_vel = _reference_filtered(pos0 + drift, vel, heading, active, actions, cfg)
    reward = np.zeros((e_n, m))
    done = np.zeros((e_n, m), dtype=bool)
    for e in range(e_n):
        was = active[e].copy()
        for i in range(m):
            if not was[i]:
                continue
            ax, ay = actions[e, i]
            norm = math.hypot(ax, ay)
            if norm > 1.0:
                ax, ay = ax / norm, ay / norm
            h = heading[e, i]
            d0 = math.hypot(*(goal[e, i] - pos[e, i] - drift[e, i]))
            vn = (ax * math.cos(h) - ay * math.sin(h)) * cfg.speed * cfg.dt_s
            ve = (ax * math.sin(h) + ay * math.cos(h)) * cfg.speed * cfg.dt_s
            if cfg.safety_filter:
                vn, ve = new_vel[e, i] * cfg.dt_s
            pos[e, i] += (vn, ve)
            if math.hypot(vn, ve) > 1e-12:
                heading[e, i] = math.atan2(ve, vn)
            reward[e, i] += cfg.w_acc * -abs(ay) + cfg.w_tme * -cfg.r_tme / trip_m[e, i]
            reward[e, i] += cfg.w_prog * (
                d0 - math.hypot(*(goal[e, i] - pos[e, i] - drift_after[e, i]))
            )
        for i in range(m):
            if not was[i]:
                continue
            hit = False
            for j in range(m):
                if j == i or not was[j]:
                    continue
                dij = math.hypot(*(pos[e, j] - pos[e, i]))
                reward[e, i] += cfg.w_cav * float(cav_reward(dij, cfg))
                if cfg.ccd:
                    (ax0, ay0), (ax1, ay1) = pos0[e, j] - pos0[e, i], pos[e, j] - pos[e, i]
                    bx, by = ax1 - ax0, ay1 - ay0
                    s = (
                        0.0
                        if bx * bx + by * by < 1e-12
                        else -(ax0 * bx + ay0 * by) / (bx * bx + by * by)
                    )
                    s = min(max(s, 0.0), 1.0)
                    dij = min(dij, math.hypot(ax0 + s * bx, ay0 + s * by))
                hit |= dij <= cfg.eps_cav_m
            arrived = math.hypot(*(goal[e, i] - pos[e, i] - drift_after[e, i])) <= cfg.eps_arr_m
            if arrived:
                reward[e, i] += cfg.w_arr * cfg.r_arr
            done[e, i] = arrived or hit or t[e] + 1 >= cfg.max_steps
        active[e] = was & ~done[e]
    return pos, heading, active, reward, done


def _reference_filtered(pos, vel, heading, active, actions, cfg: EnvConfig):
    """The commanded velocities through safety.filter_one, one vehicle at a time (`pos`: what
    the vehicles believe, with cfg.drift_m as every vehicle's sigma)."""
    e_n, m = active.shape
    out = np.zeros((e_n, m, 2))
    scfg = safety_config(cfg)
    for e in range(e_n):
        for i in range(m):
            if not active[e, i]:
                continue
            a = np.asarray(actions[e, i], dtype=np.float64)
            a = a / max(1.0, math.hypot(*a))
            h = heading[e, i]
            pref = np.array(
                [a[0] * math.cos(h) - a[1] * math.sin(h), a[0] * math.sin(h) + a[1] * math.cos(h)]
            )
            others = [j for j in range(m) if j != i and active[e, j]]
            out[e, i] = safety.filter_one(
                pos[e, i],
                vel[e, i],
                pref * cfg.speed,
                pos[e, others],
                vel[e, others],
                scfg,
                pos_sigma_m=cfg.drift_m,
                nbr_pos_sigma_m=np.full(len(others), cfg.drift_m) if cfg.drift_m > 0 else None,
            )
    return out
