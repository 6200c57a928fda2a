"""The network on observations: the clipped action (a_fwd, a_right) of one vehicle or N.

    actor = Actor(net, obs_cfg, dist_scale_m)
    a = actor.action(obs)              # policy.observation.Observation, world metres
    ref = actor.action_reference(obs)  # the plain pipeline, float64

The network sees policy units (metres / dist_scale_m); `action` takes metres and feeds them
straight to a projection that carries the scale (features.closest_last_rows), and falls back to
features.observe_fast where that does not apply. Both equal `action_reference` within 1e-5
(tests/test_policy_speed.py). policy.runtime turns the action into a velocity and filters it.
"""

from __future__ import annotations

import math

import numpy as np

from policy import features
from policy.features import ObsConfig
from policy.network import Network
from policy.observation import Observation, Observations, Swarm


def _clip_pair(a0: float, a1: float) -> tuple[float, float]:
    """(a0, a1) / |a| where |a| > 1 (features.clip_unit for one action)."""
    n = math.hypot(a0, a1)
    return (a0 / n, a1 / n) if n > 1.0 else (a0, a1)


class Actor:
    """A Network with its observation encoding and distance scale."""

    def __init__(
        self,
        net: Network,
        obs_cfg: ObsConfig,
        dist_scale_m: float,
        max_neighbours: int | None = None,
    ):
        self.net = net
        self.obs_cfg = obs_cfg
        self.dist_scale_m = float(dist_scale_m)
        """World metres per policy unit of distance (what the network sees)."""
        self.max_neighbours = max_neighbours
        # the fast path (features.closest_last_rows): the projection of rows in metres and the
        # sense range in metres; None = not this encoding
        self._rows_proj_m = None
        if (obs_cfg.encoding, obs_cfg.order) == ("sincos", "closest_last"):
            self._rows_proj_m = net.rows_projection(obs_cfg.dist_scale * self.dist_scale_m)
        self._sense_range_m = obs_cfg.sense_range * self.dist_scale_m

    def action(self, obs: Observation) -> np.ndarray:
        """Clipped action (2,) of a checked observation (policy.observation.Observation)."""
        return np.array(self.pair(obs))

    def pair(self, obs: Observation) -> tuple[float, float]:
        """`action` as two floats (the hot path builds no array): `_action_rows` where it
        applies, else features.observe_fast and Network.forward_one (the LSTM in float32
        either way)."""
        a = self._action_rows(obs)
        return self._action_seq(obs) if a is None else a

    def _action_seq(self, obs: Observation) -> tuple[float, float]:
        """The clipped action through features.observe_fast (policy units) and
        Network.forward_one: every encoding, every input."""
        s = self.dist_scale_m
        seq, goal_feat, _ = features.observe_fast(
            obs.pos_m / s,
            obs.heading_rad,
            obs.goal_m / s,
            obs.nbr_pos_m / s,
            obs.nbr_heading_rad,
            self.obs_cfg,
            self.max_neighbours,
        )
        return _clip_pair(*self.net.forward_one(seq, goal_feat))

    def _action_rows(self, obs: Observation) -> tuple[float, float] | None:
        """The clipped action through features.closest_last_rows and Network.forward_rows
        (sincos / closest_last, every neighbour kept), in metres. None where that does not
        apply (another encoding, more than max_neighbours, a neighbour on top, a non-finite
        distance)."""
        proj = self._rows_proj_m
        k = obs.nbr_pos_m.shape[0]
        if proj is None or (self.max_neighbours is not None and k > self.max_neighbours):
            return None
        net, heading = self.net, obs.heading_rad
        got = features.closest_last_rows(
            obs.nbr_pos_m - obs.pos_m,
            heading,
            obs.nbr_heading_rad,
            self._sense_range_m,
            net.rows_table(k),
        )
        if got is None:
            return None
        (p0, p1), (g0, g1) = obs.pos_m.tolist(), obs.goal_m.tolist()
        psi_d = math.atan2(g1 - p1, g0 - p0) - heading
        return _clip_pair(*net.forward_rows(got[0], proj, (math.sin(psi_d), math.cos(psi_d))))

    def action_reference(self, obs: Observation) -> np.ndarray:
        """`action` the plain way: features.observe, float64 LSTM one step at a time."""
        s = self.dist_scale_m
        seq, goal_feat, _ = features.observe(
            np.asarray(obs.pos_m) / s,
            obs.heading_rad,
            np.asarray(obs.goal_m) / s,
            np.asarray(obs.nbr_pos_m) / s,
            obs.nbr_heading_rad,
            self.obs_cfg,
            self.max_neighbours,
        )
        h = self.net.lstm_last_reference(seq)
        return features.clip_unit(self.net.head_forward(h, goal_feat))

    def action_batch(
        self, obs: Observations | Swarm, rows=None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Clipped actions (N, 2) of N vehicles, float32 like torch, and for a Swarm the
        neighbour indices (N, K) each one saw (a safety filter needs them; None for
        Observations: each row's views are its neighbours).

        `rows` (indices): run the network for these vehicles only and return their actions
        (len(rows), 2); the neighbour indices are still every vehicle's."""
        s, cfg, k = self.dist_scale_m, self.obs_cfg, self.max_neighbours
        nbr = None
        if isinstance(obs, Swarm):
            seq, lengths, goal_feat, nbr = features.observe_batch(
                obs.pos_m / s, obs.heading_rad, obs.goal_m / s, obs.active, cfg, k
            )
        else:
            seq, lengths, goal_feat, _ = features.observe_padded(
                obs.pos_m / s,
                obs.heading_rad,
                obs.goal_m / s,
                obs.nbr_pos_m / s,
                obs.nbr_heading_rad,
                obs.nbr_valid,
                cfg,
                k,
            )
        if rows is not None:
            seq, lengths, goal_feat = seq[rows], lengths[rows], goal_feat[rows]
        h = self.net.lstm_last_batch(seq, lengths)
        return features.clip_unit(self.net.head_forward(h, goal_feat)), nbr
