"""`covey eval`'s `agents` controller: every vehicle flies the agents' own guidance tick.

Each vehicle gets its own `BatchGuidance` of one row, as one `covey agent` process runs it:
the decision held for the policy's period, the sparse rule, the stale-data slowdown and the
separation filter every step, the C core where the agents use it (numpy where it leaves a call
to numpy, or without a compiler). What the link delivered becomes that row's `NeighbourViews`
(the vehicle ids, each neighbour's reported 1-sigma, the cooperative and manned flags), so the
evaluation's suites, links and vehicle models judge the guidance the agents fly, not a model
of it. The tracking compensation is policy.evalsim's, as for the other controllers.

`covey eval` enters here (`eval_cli`): policy/eval.py's command with firmware/ceval.py's
`c+filter` and this `agents` added, since policy/ and firmware/ do not import the agent built
on them. Both run only when named (`--controllers agents,policy+filter`).
"""

from __future__ import annotations

import numpy as np

from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews
from firmware.ceval import CONTROLLERS as C_CONTROLLERS
from policy import eval as policy_eval

ALT_M = 10.0
"""The altitude every vehicle flies at (guidance is planar; its vertical loop holds this)."""


class AgentFleet:
    """controller(ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid)
    of policy.evalsim: one agent's guidance tick per vehicle."""

    uses_sigma = True
    """policy.evalsim passes the position uncertainties (each view's pos_sigma_m)."""
    uses_cooperative = True
    """... and which neighbours do not cooperate, and which are manned aircraft."""

    def __init__(self, cfg: GuidanceConfig, safety_cfg) -> None:
        """`cfg`: the agents' guidance settings; `safety_cfg`: the evaluation's filter settings
        (policy.safety.SafetyConfig, so that --sigma-k and the berths reach the agents too)."""
        self.cfg = cfg
        self.policy = cfg.load_policy(safety_cfg)
        self.safety_cfg = self.policy.safety_cfg
        self._rows: dict[int, BatchGuidance] = {}
        self._zones_m: list | None = None

    def reset(self) -> None:
        """A new scenario: every vehicle forgets its held decision, and the zones."""
        self._rows, self._zones_m = {}, None

    def set_zones(self, zones_m) -> None:
        """Keep-out polygons [(K, 2)] for this scenario: every vehicle routes around them and
        filters against their edges itself (BatchGuidance.set_zones, as an agent given the
        fleet plan; policy/zone_eval.py calls this instead of routing for it)."""
        self._zones_m = [np.asarray(z, float) for z in zones_m]
        for g in self._rows.values():
            g.set_zones(self._zones_m)

    def _guidance(self, vid: int) -> BatchGuidance:
        g = self._rows.get(vid)
        if g is None:
            g = self._rows[vid] = BatchGuidance(self.cfg, 1, self.policy)
            if self._zones_m:
                g.set_zones(self._zones_m)
        return g

    @property
    def c_core_calls(self) -> dict:
        """The C core's calls over the vehicles flown since `reset` (agent/guidance_c.py)."""
        total: dict = {}
        for g in self._rows.values():
            for k, v in ({} if g.c_core is None else g.c_core.calls).items():
                total[k] = total.get(k, 0) + v
        return total

    def __call__(
        self, ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **sky
    ):
        """`sky`: policy.evalsim's pos_sigma_m (N,), nbr_pos_sigma_m, nbr_cooperative and
        nbr_manned (N, K), each only when the scenario has it."""
        out = np.zeros((len(ids), 2))
        here = np.array([0])
        for row, vid in enumerate(np.asarray(ids).tolist()):
            m = np.flatnonzero(nbr_valid[row])
            views = _views(row, m, vid, nbr_pos, nbr_vel, nbr_heading, sky)
            step = self._guidance(vid).step(
                float(t_s),
                here,
                _ned(pos[row : row + 1]),
                _ned(vel[row : row + 1], 0.0),
                np.asarray(heading[row : row + 1], float),
                _ned(goal[row : row + 1]),
                np.zeros(1, bool),
                views,
            )
            out[row] = step.vel_ned_m_s[0, :2]
        return out


def _ned(xy: np.ndarray, down_m: float = -ALT_M) -> np.ndarray:
    """(k, 2) north/east -> (k, 3) NED at the evaluation's altitude (or `down_m`)."""
    xy = np.asarray(xy, float)
    return np.column_stack([xy, np.full(len(xy), down_m)])


def _views(row, m, vid, nbr_pos, nbr_vel, nbr_heading, sky: dict) -> NeighbourViews:
    """One agent's view of the neighbours `m` its link delivered (evaluation rows are the ids:
    vehicle id = row + 1, so coincident vehicles are untied as the agents untie them)."""
    k = m.size

    def column(name: str, dtype):
        x = sky.get(name)
        return None if x is None else np.asarray(x[row, m], dtype)

    own = sky.get("pos_sigma_m")
    own_sigma = 0.0 if own is None else float(own[row])
    sigma = column("nbr_pos_sigma_m", float)
    coop = column("nbr_cooperative", bool)
    manned = column("nbr_manned", bool)
    return NeighbourViews(
        _ned(nbr_pos[row, m]).reshape(1, k, 3),
        _ned(nbr_vel[row, m], 0.0).reshape(1, k, 3),
        np.asarray(nbr_heading[row, m], float).reshape(1, k),
        np.ones((1, k), bool),
        np.zeros((1, k), bool),
        (m + 1).astype(np.int64).reshape(1, k),
        np.array([vid + 1], np.int64),
        None if sigma is None or not sigma.any() else sigma.reshape(1, k),
        None if coop is None or coop.all() else coop.reshape(1, k),
        np.array([own_sigma]) if own_sigma else None,
        None if manned is None or not manned.any() else manned.reshape(1, k),
    )


def agents(cfg: policy_eval.EvalConfig, safety_cfg) -> AgentFleet:
    """The `agents` controller: `covey agent`'s guidance (the C core on, as the agents fly),
    with the evaluation's weights (`--weights`), told separation (`--policy-separation-m`) and
    filter settings."""
    guidance = GuidanceConfig(
        c_core=True, policy_path=cfg.weights, policy_separation_m=cfg.policy_separation_m
    )
    return AgentFleet(guidance, safety_cfg)


CONTROLLERS: dict[str, policy_eval.ControllerFactory] = {**C_CONTROLLERS, "agents": agents}
"""What `covey eval` adds to policy/eval.py's controllers; each runs only when named."""


def main(cfg: policy_eval.EvalConfig) -> dict:
    """policy.eval.main with the C core's and the agents' controllers available."""
    return policy_eval.main(cfg, CONTROLLERS)


def eval_cli(argv=None) -> dict:
    """`covey eval`: policy.eval.cli with the C core's and the agents' controllers available."""
    return policy_eval.cli(argv, CONTROLLERS)


def eval_parser():
    """`covey eval`'s parser (policy.eval's; covey_cli finds it beside `eval_cli`)."""
    return policy_eval.parser()
