"""`covey eval` controller that flies the C core as the PX4 module does (`c+filter`).

Each vehicle runs its own covey_guidance_step (firmware/covey_guidance.c): the C policy
decides at the trained period, the velocity is held in between, and the C separation filter
runs at every simulation step against what the link delivered. Nothing of the numpy runtime
is in the loop, so `covey eval --controllers c+filter,policy+filter,orca` compares the onboard
C core with the companion's numpy runtime on the same cases.

`covey eval` (agent/eval_agents.py) adds `c+filter` to policy/eval.py's command, since policy/
does not import the firmware built on it.
"""

from __future__ import annotations

import numpy as np

from firmware.csafety import MAX_INPUTS
from policy import eval as policy_eval
from policy.observation import Observation, Sky


class COnboardFleet:
    """controller(ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid)
    of policy.evalsim, one C guidance tick per vehicle."""

    def __init__(self, policy, decision_period_s: float):
        """`policy` is a firmware.cpolicy.CPolicy (its filter setting and config are used)."""
        self.policy = policy
        self.decision_period_s = float(decision_period_s)
        self._ticks: dict = {}

    def reset(self) -> None:
        """A new scenario: every vehicle forgets its held decision."""
        self._ticks = {}

    def zone_filter(self, zones_m, radius_m: float, time_horizon_s: float):
        """The C keep-out zones on this controller's library (firmware.czones.CZones), for
        policy.zone_eval's c+filter."""
        from firmware.czones import CZones

        return CZones(self.policy._lib, zones_m, radius_m, time_horizon_s)

    def _tick(self, vid: int):
        t = self._ticks.get(vid)
        if t is None:
            t = self._ticks[vid] = self.policy.onboard(self.decision_period_s)
        return t

    uses_sigma = True
    """policy.evalsim passes the position uncertainties (covey_guidance_step_sky)."""
    uses_cooperative = True
    """... and which neighbours do not cooperate (intruders: the C filter's non_cooperative;
    manned aircraft: COVEY_TRACK_MANNED)."""

    def __call__(
        self,
        ids,
        t_s,
        pos,
        vel,
        heading,
        goal,
        nbr_pos,
        nbr_vel,
        nbr_heading,
        nbr_valid,
        pos_sigma_m=None,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ):
        out = np.zeros((len(ids), 2))
        for row, vid in enumerate(np.asarray(ids).tolist()):
            m = np.flatnonzero(nbr_valid[row])
            if m.size > MAX_INPUTS:  # the C core takes 64 reports: keep the nearest, in order
                d = ((nbr_pos[row, m] - pos[row]) ** 2).sum(-1)
                if nbr_cooperative is not None:  # traffic first, however far: it never avoids
                    d = np.where(nbr_cooperative[row, m], d, -1.0)
                m = np.sort(m[np.argsort(d, kind="stable")[:MAX_INPUTS]])
            obs = Observation.shaped(
                pos[row],
                vel[row],
                heading[row],
                goal[row],
                nbr_pos[row, m],
                nbr_vel[row, m],
                nbr_heading[row, m],
                Sky(
                    0.0 if pos_sigma_m is None else float(pos_sigma_m[row]),
                    None if nbr_pos_sigma_m is None else nbr_pos_sigma_m[row, m],
                    None if nbr_cooperative is None else nbr_cooperative[row, m],
                    None if nbr_manned is None else nbr_manned[row, m],
                ),
            )
            r = self._tick(vid).step(obs, t_s)
            if r.status != "ok":
                raise RuntimeError(
                    f"C guidance fault for vehicle {vid} at t={t_s:.2f} s: {r.status}"
                )
            out[row] = r.vel_m_s
        return out


def c_filter(cfg: policy_eval.EvalConfig, safety_cfg) -> COnboardFleet:
    """The `c+filter` controller: the C policy with the C filter at policy+filter's settings
    (`safety_cfg`, policy.safety.SafetyConfig: it keeps 3 m, as policy+filter does)."""
    from firmware.cpolicy import CPolicy
    from policy.pointmass import VehicleModel
    from policy.runtime import filtered_told_share, told_separation_m

    inflation_m = 0.0
    if cfg.tell_inflation:
        sigma_m = VehicleModel.named(cfg.vehicles).pos_sigma_m
        inflation_m = policy_eval.inflation_told_m(safety_cfg, sigma_m)
    cpol = CPolicy.load(
        cfg.weights,
        separation_m=safety_cfg.radius_m,
        policy_separation_m=told_separation_m(
            safety_cfg.radius_m,
            True,
            cfg.policy_separation_m,
            inflation_m,
            filtered_told_share(cfg.weights),
        ),
        max_neighbours=cfg.max_neighbours,
        safety_cfg=safety_cfg,
        sparse_rule=cfg.sparse_rule,
        told_sigma_free_m=policy_eval.told_sigma_free_m(cfg),
    )
    return COnboardFleet(cpol, cfg.policy_period_s)


CONTROLLERS: dict[str, policy_eval.ControllerFactory] = {"c+filter": c_filter}
"""What `covey eval` adds to policy/eval.py's controllers; each runs only when named (it needs
a C compiler)."""


def main(cfg: policy_eval.EvalConfig) -> dict:
    """policy.eval.main with the C core's controllers available."""
    return policy_eval.main(cfg, CONTROLLERS)
