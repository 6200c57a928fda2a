"""Shared by the traffic tests (tests/test_traffic_*.py): one vehicle's scene through numpy's
three filter paths, and through C beside numpy's reference, every position 1-sigma alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from policy import safety


def three_paths(cfg, pos, vel, pref, nbr_p, nbr_v, coop, sigma_m: float = 0.5):
    """(filter_one, filter_velocity, filter_padded) of the scene: the vehicle at pos with
    velocity vel wanting pref, neighbours nbr_p / nbr_v (K, 2), cooperative flags coop (K,)."""
    sig = np.full(len(nbr_p), sigma_m)
    sky: dict[str, Any] = {"pos_sigma_m": sigma_m, "nbr_pos_sigma_m": sig, "nbr_cooperative": coop}
    a, b = (
        f(pos, vel, pref, nbr_p, nbr_v, cfg, **sky)
        for f in (safety.filter_one, safety.filter_velocity)
    )
    c = safety.filter_padded(
        pos[None],
        vel[None],
        pref[None],
        nbr_p[None],
        nbr_v[None],
        np.ones((1, len(nbr_p)), bool),
        cfg,
        pos_sigma_m=np.array([sigma_m]),
        nbr_pos_sigma_m=sig[None],
        nbr_cooperative=coop[None],
    )[0]
    return a, b, c


def c_and_reference(c_filter, cfg, pos, vel, pref, nbr_p, nbr_v, coop, sigma_m: float = 0.5):
    """(C's result (firmware.csafety.CSafetyFilter.evaluate), numpy's filter_velocity) of the
    scene as `three_paths` takes it."""
    sky: dict[str, Any] = {
        "pos_sigma_m": sigma_m,
        "nbr_pos_sigma_m": np.full(len(nbr_p), sigma_m),
        "nbr_cooperative": coop,
    }
    r = c_filter.evaluate(pos, vel, pref, nbr_p, nbr_v, **sky)
    ref = safety.filter_velocity(pos, vel, pref, nbr_p, nbr_v, cfg, **sky)
    return r, ref


def c_filter(cfg):
    """The C core's filter (firmware.csafety.CSafetyFilter) at `cfg`; needs a C compiler."""
    from firmware.cpolicy import load_library
    from firmware.csafety import CSafetyFilter

    return CSafetyFilter(load_library(), cfg)


ISSUE16_WEIGHTS = (
    Path(__file__).resolve().parent.parent / "policy" / "weights" / "policy_issue16.npz"
)
"""Issue 16's weights, with which the seeded regression scenes of this suite were found."""


def intruder_run(
    seed: int,
    case: str,
    controller: str,
    link: str,
    suite: str = "intruder",
    recover_speed_share: float | None = None,
    vehicles: str = "realistic",
    weights: str | None = None,
):
    """One run of `covey eval --suites <suite> --vehicles <vehicles> --controllers
    policy+filter,c+filter --seed <seed>`, with that command's random draws: the case `case` of
    `suite` ("intruder" or "manned") flown by `controller` ("policy+filter" or "c+filter", which
    needs a C compiler) on `link` ("perfect" or "degraded"). Module constants are read as the
    run flies, so a test may monkeypatch them first. `recover_speed_share`: `covey eval
    --recover-speed-share` (0: the parting rule before policy.safety.RECOVER_SPEED_SHARE);
    `vehicles`: `covey eval --vehicles`; `weights`: `covey eval --weights` (None: the shipped
    ones). Returns evalsim.run's metrics."""
    from firmware.ceval import CONTROLLERS
    from policy import eval as ev
    from policy import evalsim
    from policy.pointmass import VehicleModel
    from policy.tracking import TrackingConfig

    ctrls = ("policy+filter", "c+filter")
    links = ("perfect", "degraded")
    cfg = ev.EvalConfig(
        seed=seed,
        suites=(suite,),
        vehicles=vehicles,
        progress=False,
        controllers=ctrls,
        recover_speed_share=recover_speed_share,
        weights=weights,
    )
    index = {c[1]: (i, c) for i, c in enumerate(ev.cases(cfg))}
    i, (_, _, starts, goals, opts) = index[case]
    ctrl = ev.controllers(cfg, CONTROLLERS if controller == "c+filter" else None)[controller]
    model = VehicleModel.named(vehicles)
    sim = evalsim.EvalSimConfig(vehicles=model, tracking=TrackingConfig.assumed(model, True))
    ctrl.reset()
    # covey eval's run index: cases x links x controllers, in that order
    run = (i * len(links) + links.index(link)) * len(ctrls) + ctrls.index(controller)
    net = evalsim.PERFECT if link == "perfect" else evalsim.DEGRADED
    return evalsim.run(starts, goals, ctrl, net, sim, np.random.default_rng([seed, run]), **opts)


def without_kept_side(monkeypatch) -> None:
    """The side rule as it was before policy.traffic_rules.kept_offset: the offset from the
    neighbour's track as it is now, wherever the vehicle is going (for closed-loop tests that
    measure another rule, which the kept side alone also keeps clear)."""
    from policy import traffic_rules

    def now(px, py, jx, jy, *_):
        return px * jy - py * jx

    monkeypatch.setattr(traffic_rules, "kept_offset", now)
    monkeypatch.setattr(traffic_rules, "kept_offset_one", now)


def assert_c_matches_numpy(cfg, scenes, tol_m_s: float = 1e-4) -> None:
    """Every scene (pos, vel, pref, nbr_p, nbr_v, coop) through the C filter and numpy's
    reference (`c_and_reference`): C says ok and equals numpy within `tol_m_s`. Needs a C
    compiler."""
    f = c_filter(cfg)
    for scene in scenes:
        r, ref = c_and_reference(f, cfg, *scene)
        assert r.status == "ok" and np.abs(r.vel_m_s - ref).max() <= tol_m_s, (r.vel_m_s, ref)
