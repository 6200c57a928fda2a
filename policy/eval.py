"""`covey eval`: scenario suites, baselines, metrics, tables and figures.

    covey eval --quick                       # smoke run, a minute
    covey eval --out runs/eval --paper-weights runs/paper/final.npz \
        --occupancy runs/occupancy/final.pt

Suites (policy units): antipodal circle (N up to 50), random forced conflicts
(N = 2-10), random large swarms (N = 35 and 100); links perfect and degraded
(3 Hz, 20 % loss, 100 ms latency). Controllers: the policy with and without the
safety filter, optional paper-config and occupancy-map policies, ORCA and the
straight line; and controllers that a higher layer adds, which run only when named (`covey eval`
adds `c+filter`, the C core as flown onboard). Writes results.json, results.md, trajectory PNGs
and the paper's Fig. 5 heading-change maps.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policy import evalsim, scenarios
from policy.evalsim import DEGRADED, PERFECT, EvalSimConfig
from policy.observation import Observations
from policy.pointmass import VehicleModel
from policy.tracking import TrackingConfig


def flops(n: int, h: int = 63, x: int = 3, layers=(64, 64), a: int = 2) -> int:
    """FLOPs of one policy evaluation with n vehicles (the paper's formula).

    (n-1)(8h^2 + 8hx + 26h) + 2(h+1)l1 + 4l1 + sum_k (2 l_k l_k+1 + 4 l_k+1) + 2 l_w a + 4a
    """
    per_nbr = 8 * h * h + 8 * h * x + 26 * h
    fixed = 2 * (h + 1) * layers[0] + 4 * layers[0]
    fixed += sum(2 * layers[k] * layers[k + 1] + 4 * layers[k + 1] for k in range(len(layers) - 1))
    fixed += 2 * layers[-1] * a + 4 * a
    return (n - 1) * per_nbr + fixed


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate and where to write it."""

    out: str = "runs/eval"
    """Output directory."""
    weights: str | None = None
    """Policy weights (.npz); None = the shipped ones."""
    paper_weights: str | None = None
    """Optional weights of a paper-configuration policy to compare."""
    occupancy: str | None = None
    """Optional trainer checkpoint (.pt) of the occupancy-map baseline (needs torch)."""
    max_neighbours: int = 10
    """Nearest neighbours fed to the learned policies."""
    policy_separation_m: float | None = None
    """Separation the learned policies are told to keep (collisions are still counted below
    3 m). None: as flight tells them (policy.runtime.told_separation_m): the share of 3 m the
    weights' config states with a filter (policy+filter, c+filter; the shipped weights: all of
    it; weights without one: 1.25 m), 3 m without, growing with GNSS worse than 0.5 m
    (policy.runtime.told_scale). Given: told as given, whatever the GNSS."""
    sparse_rule: bool = True
    """Filtered learned policies (policy+filter, c+filter) fly straight where a vehicle meets at
    most two others (a vehicle that stands and is passed clear is none) and not dead-on, as the
    agents do (policy.sparse); off: the policy always."""
    quick: bool = False
    """Small smoke suite."""
    seed: int = 0
    """Scenario and link-loss seed."""
    links: tuple = ("perfect", "degraded")
    """Link models to run: perfect, degraded (3 Hz, 20 % loss, 100 ms)."""
    dt_s: float = 0.1
    """Simulation step (links, safety filter, collision checks)."""
    policy_period_s: float = 1.0
    """Learned policies decide every period (their training step) and hold in between."""
    dead_reckon: bool = True
    """Receivers dead-reckon neighbours' last states to now, as the agents do (degraded link;
    --no-dead-reckon: use them as they came, the evaluation before issue 16's step 3)."""
    figures: bool = True
    """Write trajectory PNGs and the Fig. 5 maps."""
    progress: bool = True
    """Show a tqdm bar."""
    suites: tuple = field(default=("circle", "conflict", "large"))
    """Scenario suites to run: circle, conflict, large, intruder (a vehicle that does not
    cooperate flies straight through at 1x, 1.5x and 2x the fleet's speed), manned (a manned
    aircraft flies through at 20, 40 and 60 m/s, heard 30 s before: the fleet keeps its 30 m
    berth), zones (keep-out zones, routed gotos: policy/zone_eval.py)."""
    vehicles: str = "ideal"
    """How the vehicles fly (policy.pointmass.VehicleModel): ideal (exactly what is commanded,
    exact positions) or realistic (0.3 s velocity lag, 2.5 m/s^2, 0.2 m/s gusts, GNSS estimate
    drifting 0.5 m), optionally with fields changed (realistic:drift_m=1.0,gust_m_s=0.4);
    collisions and min_sep are judged on true positions, est_* on estimates."""
    tracking: bool = True
    """Take each vehicle's tracking error (gusts its loop does not reject, a loop slower than
    assumed) off its next command, as the agents do (policy/tracking.py); off: commands go as
    the controller made them (before). Intruders are never corrected."""
    tracking_lag_s: float | None = None
    """The velocity-loop lag the tracking compensation assumes; None: the vehicles' own (as an
    agent on a simulated vehicle does). Another value measures a model that is wrong."""
    sigma_k: float | None = None
    """Confidence factor of the filter's uncertainty inflation (policy.safety.SafetyConfig.sigma_k,
    None = its default); 0: the filter takes the estimates as the truth."""
    recover_speed_share: float | None = None
    """How fast a pair inside its uncertainty padding (not the separation itself) is asked to
    part, as a share of the speed limit (policy.safety.SafetyConfig.recover_speed_share, None =
    its default: 2, each vehicle at up to its full speed); 0: within one control period, as RVO2
    does (before)."""
    tell_inflation: bool = False
    """Tell the learned policies the separation inflated by the whole uncertainty, fixed at the
    vehicles' sigma (policy.runtime.told_separation_m's inflation_m); off: as flight tells
    them (beyond 0.5 m GNSS, the excess only: policy.runtime.told_scale)."""
    non_cooperative_separation_m: float | None = None
    """Separation the filter keeps from vehicles that do not cooperate (intruder suite;
    policy.safety.SafetyConfig.non_cooperative_radius_m); None: the separation."""
    mark_non_cooperative: bool = True
    """Tell the controllers which vehicles do not cooperate (the filter takes the whole
    correction for them); off: they take intruders for covey vehicles (before issue 35)."""
    controllers: tuple = ()
    """Run only these controllers, e.g. policy,orca (empty = all available but c+filter, the C
    core as onboard, and agents, the agents' own guidance tick (agent/eval_agents.py), which
    run only when named)."""


def cases(cfg: EvalConfig):
    """[(suite, name, starts, goals)], or (suite, name, starts, goals, run options) where a case
    has intruders (evalsim.run's non_cooperative and speed_m_s)."""
    rng = np.random.default_rng(cfg.seed)
    out = []
    circle = [4, 8] if cfg.quick else [2, 4, 8, 16, 32, 50]
    conflict = (
        [(3, 0), (6, 0)] if cfg.quick else [(n, s) for n in (2, 4, 6, 8, 10) for s in range(3)]
    )
    large = [(35, 0)] if cfg.quick else [(35, 0), (35, 1), (100, 0)]
    if "circle" in cfg.suites:
        out += [("circle", f"circle-{n}", *scenarios.antipodal_circle(n)) for n in circle]
    if "conflict" in cfg.suites:
        out += [
            ("conflict", f"conflict-{n}-s{s}", *scenarios.random_conflict(rng, n))
            for n, s in conflict
        ]
    if "large" in cfg.suites:
        out += [("large", f"large-{n}-s{s}", *scenarios.random_large(rng, n)) for n, s in large]
    if "zones" in cfg.suites:  # keep-out zones (policy/zone_eval.py)
        for name, starts, goals, zones_m in scenarios.zone_scenes(rng, cfg.quick):
            out.append(("zones", f"zones-{name}", starts, goals, {"zones_m": zones_m}))
    if "intruder" in cfg.suites:
        for ratio in scenarios.INTRUDER_SPEED_RATIOS:
            for name, starts, goals, nc, speeds in scenarios.intruder_cases(rng, ratio, cfg.quick):
                options = {"non_cooperative": nc, "speed_m_s": speeds}
                out.append(("intruder", f"intruder-{ratio:g}x-{name}", starts, goals, options))
    if "manned" in cfg.suites:
        for speed in scenarios.MANNED_SPEEDS_M_S:
            for name, starts, goals, nc, speeds, manned in scenarios.manned_cases(
                rng, speed, cfg.quick
            ):
                options = {"non_cooperative": nc, "speed_m_s": speeds, "manned": manned}
                out.append(("manned", f"manned-{speed:g}m_s-{name}", starts, goals, options))
    return out


ControllerFactory = Callable[[EvalConfig, Any], Callable]
"""factory(cfg, safety_cfg) -> controller: an extra controller, built only when named (it may
need what the built-in ones do not, such as a C compiler). safety_cfg is policy.safety's
SafetyConfig that policy+filter flies with."""


def controllers(cfg: EvalConfig, extra: Mapping[str, ControllerFactory] | None = None) -> dict:
    """name -> controller(pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid).
    `extra` controllers are built only when cfg.controllers names them."""
    from policy.pointmass import VehicleModel
    from policy.runtime import GuidancePolicy, filtered_told_share, told_separation_m
    from policy.safety import SafetyConfig, filter_padded
    from policy.sparse import SparseConfig

    safety_cfg = SafetyConfig(dt_s=cfg.dt_s)
    if cfg.recover_speed_share is not None:
        safety_cfg = dataclasses.replace(safety_cfg, recover_speed_share=cfg.recover_speed_share)
    if cfg.sigma_k is not None:
        safety_cfg = dataclasses.replace(safety_cfg, sigma_k=cfg.sigma_k)
    if cfg.non_cooperative_separation_m is not None:
        safety_cfg = dataclasses.replace(
            safety_cfg, non_cooperative_radius_m=cfg.non_cooperative_separation_m
        )
    sigma_m = VehicleModel.named(cfg.vehicles).pos_sigma_m
    inflation_m = inflation_told_m(safety_cfg, sigma_m) if cfg.tell_inflation else 0.0
    out: dict[str, Callable[..., Any]] = {}
    for name, path, filt in [
        ("policy+filter", cfg.weights, True),
        ("policy", cfg.weights, False),
        ("paper-config", cfg.paper_weights, False),
    ]:
        if name == "paper-config" and not path:
            continue
        pol = GuidancePolicy.load(
            path,
            separation_m=safety_cfg.radius_m,
            policy_separation_m=told_separation_m(
                safety_cfg.radius_m,
                filt,
                cfg.policy_separation_m,
                inflation_m if filt else 0.0,
                filtered_told_share(path),
            ),
            safety_filter=False,
            max_neighbours=cfg.max_neighbours,
            sparse_rule=SparseConfig() if filt and cfg.sparse_rule else None,
            safety_cfg=safety_cfg,  # the sparse rule's filter: --sigma-k reaches it too
            told_sigma_free_m=told_sigma_free_m(cfg),
        )
        out[name] = Held(_decide_views(pol), cfg.policy_period_s, safety_cfg if filt else None)
    if cfg.occupancy:
        out["occupancy"] = Held(
            _occupancy_controller(cfg.occupancy, cfg.max_neighbours), cfg.policy_period_s
        )

    def orca(ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **sig):
        v = evalsim.straight_line(ids, t_s, pos, vel, heading, goal)
        return filter_padded(
            pos,
            vel,
            v,
            nbr_pos,
            nbr_vel,
            nbr_valid,
            safety_cfg,
            pos_sigma_m=sig.get("pos_sigma_m"),
            nbr_pos_sigma_m=sig.get("nbr_pos_sigma_m"),
            nbr_cooperative=sig.get("nbr_cooperative"),
            nbr_manned=sig.get("nbr_manned"),
        )

    # capability flags evalsim reads off a controller; the zone suite filters with the same config
    vars(orca).update(uses_sigma=True, safety_cfg=safety_cfg, uses_cooperative=True)
    out["orca"] = orca
    out["straight"] = evalsim.straight_line
    for name, make in (extra or {}).items():
        if name in cfg.controllers:
            out[name] = make(cfg, safety_cfg)
    return out


def told_sigma_free_m(cfg: EvalConfig) -> float | None:
    """policy.runtime.TOLD_SIGMA_FREE_M, as the agents fly; None where the policy's berth is
    asked for (--policy-separation-m, --tell-inflation): told as asked."""
    from policy.runtime import TOLD_SIGMA_FREE_M

    asked = cfg.policy_separation_m is not None or cfg.tell_inflation
    return None if asked else TOLD_SIGMA_FREE_M


def inflation_told_m(safety_cfg, sigma_m: float) -> float:
    """What the filter adds to a pair's distance when both vehicles report sigma_m:
    sigma_k sqrt(2) sigma_m (policy.safety.pair_radius_m), told to the policy with
    --tell-inflation."""
    return float(safety_cfg.sigma_k * np.sqrt(2.0) * sigma_m)


def _decide_views(pol):
    """`pol.command_batch` on each vehicle's padded views, as the controllers here are called;
    it takes the position uncertainties (`takes_sigma`) for its sparse rule."""

    def decide(pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **sky):
        obs = Observations(pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **sky)
        return pol.command_batch(obs)

    decide.takes_sigma = True
    return decide


class Held:
    """Runs a learned policy every period_s (its training step) and holds the velocity in
    between; the optional safety filter runs at every simulation step, with the position
    uncertainties when the simulator passes them."""

    uses_sigma = True
    uses_cooperative = True

    def __init__(self, policy, period_s: float, safety_cfg=None):
        self.policy, self.period_s, self.safety_cfg = policy, period_s, safety_cfg
        self.v: dict = {}
        self.next_t = -1.0

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
        from policy.safety import filter_padded

        if t_s < self.next_t - 1e-9 and self.v and t_s > 0:
            v = np.array([self.v[i] for i in ids])
        else:
            sky = {}
            if pos_sigma_m is not None and getattr(self.policy, "takes_sigma", False):
                sky = {"pos_sigma_m": pos_sigma_m, "nbr_pos_sigma_m": nbr_pos_sigma_m}
            v = self.policy(
                pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **sky
            )
            self.v = dict(zip(ids.tolist(), v, strict=True))
            self.next_t = t_s + self.period_s
        if self.safety_cfg is not None:
            v = filter_padded(
                pos,
                vel,
                v,
                nbr_pos,
                nbr_vel,
                nbr_valid,
                self.safety_cfg,
                pos_sigma_m=pos_sigma_m,
                nbr_pos_sigma_m=nbr_pos_sigma_m,
                nbr_cooperative=nbr_cooperative,
                nbr_manned=nbr_manned,
            )
        return v

    def reset(self):
        self.v, self.next_t = {}, -1.0


def _occupancy_controller(ckpt: str, max_neighbours: int):
    import torch

    from policy import features
    from policy.export import load_checkpoint

    model, _ = load_checkpoint(ckpt)
    obs = model.cfg.obs

    def ctrl(pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid):
        seq, lengths, g, _ = features.observe_padded(
            pos, heading, goal, nbr_pos, nbr_heading, nbr_valid, obs, max_neighbours
        )
        with torch.no_grad():
            a = model.actor_mean(
                torch.tensor(seq, dtype=torch.float32),
                torch.tensor(lengths),
                torch.tensor(g, dtype=torch.float32),
            ).numpy()
        return features.action_to_velocity(features.clip_unit(a), heading)

    return ctrl


def summarise(rows: list) -> list:
    """One row per (controller, link, suite)."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["controller"], r["link"], r["suite"]), []).append(r)
    out = []
    for (c, link, suite), rs in groups.items():

        def mean(key, rs=rs):
            v = [r[key] for r in rs if r[key] is not None]
            return float(np.mean(v)) if v else None

        seps = [r["min_sep"] for r in rs if r["min_sep"] is not None]
        est_seps = [r["est_min_sep"] for r in rs if r.get("est_min_sep") is not None]
        out.append(
            {
                "controller": c,
                "link": link,
                "suite": suite,
                "cases": len(rs),
                "vehicles": int(sum(r["n"] for r in rs)),
                "success": float(np.mean([r["success"] for r in rs])),
                "collisions": int(sum(r["collisions"] for r in rs)),
                "collision_cases": int(sum(r["collisions"] > 0 for r in rs)),
                "timeouts": int(sum(r["timeouts"] for r in rs)),
                "min_sep": float(min(seps)) if seps else None,
                "est_min_sep": float(min(est_seps)) if est_seps else None,
                "est_collisions": int(sum(r.get("est_collisions", 0) for r in rs)),
                "extra_time": mean("extra_time"),
                "path_ratio": mean("path_ratio"),
                "mean_acc": mean("mean_acc"),
                **(
                    {
                        "zone_entries": int(sum(r["zone_entries"] for r in rs)),
                        "arrived": int(sum(r["arrived"] for r in rs)),
                        "refused": int(sum(r.get("refused", 0) for r in rs)),
                        "min_zone_m": min(
                            (float(r["min_zone_m"]) for r in rs if r["min_zone_m"] is not None),
                            default=None,
                        ),
                        "route_time": mean("route_time"),
                    }
                    if all("zone_entries" in r for r in rs)
                    else {}
                ),
                **(
                    {
                        "manned_entries": int(sum(r["manned_entries"] for r in rs)),
                        "manned_min_sep": min(
                            (r["manned_min_sep"] for r in rs if r["manned_min_sep"] is not None),
                            default=None,
                        ),
                    }
                    if suite == "manned"
                    else {}
                ),
            }
        )
    return out


def markdown(summary: list) -> str:
    cols = [
        "suite",
        "link",
        "controller",
        "cases",
        "vehicles",
        "success",
        "collisions",
        "collision_cases",
        "timeouts",
        "min_sep",
        "est_min_sep",
        "extra_time",
        "path_ratio",
        "mean_acc",
    ]
    if any("zone_entries" in s for s in summary):  # the zones suite's counts
        cols += ["zone_entries", "arrived", "refused", "min_zone_m", "route_time"]
    if any("manned_entries" in s for s in summary):  # the manned suite's berth
        cols += ["manned_entries", "manned_min_sep"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for s in sorted(summary, key=lambda s: (s["suite"], s["link"], s["controller"])):
        cells = []
        for c in cols:
            v = s.get(c)
            cells.append("-" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(cfg: EvalConfig, extra_controllers: Mapping[str, ControllerFactory] | None = None) -> dict:
    """Runs every (case, link, controller); writes results.json and results.md.
    `extra_controllers`: see `controllers`."""
    from tqdm import tqdm

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ctrls = controllers(cfg, extra_controllers)
    if cfg.controllers:
        unknown = set(cfg.controllers) - set(ctrls)
        if unknown:
            raise ValueError(
                f"unknown or unavailable controllers {sorted(unknown)}; have {sorted(ctrls)}"
            )
        ctrls = {k: v for k, v in ctrls.items() if k in cfg.controllers}
    links = {"perfect": PERFECT, "degraded": DEGRADED}
    vehicles = VehicleModel.named(cfg.vehicles)
    tracking = TrackingConfig.assumed(vehicles, cfg.tracking, cfg.tracking_lag_s)
    all_cases = cases(cfg)
    rows: list[dict] = []
    tracks: dict = {}
    zone_tracks: dict = {}
    jobs = [(c, ln, name) for c in all_cases for ln in cfg.links for name in ctrls]
    for (suite, case, starts, goals, *options), link, name in tqdm(
        jobs, disable=not cfg.progress, unit="run"
    ):
        record = (
            cfg.figures and link == "perfect" and case in ("circle-16", "circle-8", "large-35-s0")
        )
        sim_cfg = EvalSimConfig(
            dt_s=cfg.dt_s,
            record=record,
            dead_reckon=cfg.dead_reckon,
            vehicles=vehicles,
            tracking=tracking,
        )
        rng = np.random.default_rng([cfg.seed, len(rows)])
        if hasattr(ctrls[name], "reset"):
            ctrls[name].reset()
        if not cfg.mark_non_cooperative and getattr(ctrls[name], "uses_cooperative", False):
            ctrls[name].uses_cooperative = False  # intruders taken for covey vehicles
        opts = dict(options[0]) if options else {}
        zones_m = opts.pop("zones_m", None)
        if zones_m is not None:
            from policy import zone_eval

            r = zone_eval.run(
                name, starts, goals, zones_m, ctrls[name], links[link], sim_cfg, rng, **opts
            )
            tr, gl = r.pop("tracks"), r.pop("goals")
            flew = tr.size > 0  # every goto refused: nothing to draw
            if flew and cfg.figures and link == "perfect" and name in ("policy+filter", "c+filter"):
                zone_tracks.setdefault(name, []).append((case, tr, gl, zones_m))
        else:
            r = evalsim.run(starts, goals, ctrls[name], links[link], sim_cfg, rng, **opts)
        if record:
            tracks[(case, name)] = (r.pop("tracks"), r.pop("goals"))
        rows.append({"suite": suite, "case": case, "link": link, "controller": name, **r})
    summary = summarise(rows)
    result = {"config": asdict(cfg), "flops_20": flops(20), "summary": summary, "runs": rows}
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(markdown(summary))
    if cfg.figures:
        from policy import figures

        for (case, name), (tr, goals) in tracks.items():
            figures.plot_tracks(tr, goals, f"{case} / {name}", out / f"tracks_{case}_{name}.png")
        for name, flown in zone_tracks.items():
            from policy import zone_eval

            panels = [(f"{case} / {name}", tr, gl, z) for case, tr, gl, z in flown[:4]]
            zone_eval.plot_scenes(panels, out / f"tracks_zones_{name}.png")
        from policy.runtime import GuidancePolicy

        pol = GuidancePolicy.load(cfg.weights, safety_filter=False)
        figures.heading_change_maps(pol, out / "fig5_heading_change.png")
    return result


def merge(paths, out: str | Path) -> dict:
    """Combines the runs of several results.json files into one table."""
    rows = []
    for p in paths:
        rows += json.loads(Path(p).read_text())["runs"]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "merged": [str(p) for p in paths],
        "flops_20": flops(20),
        "summary": summarise(rows),
        "runs": rows,
    }
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(markdown(result["summary"]))
    return result


def parser() -> argparse.ArgumentParser:
    """One flag per EvalConfig field (help: the docstring under it), plus --merge."""
    from cli.options import add_config_flags, finite, renamed
    from policy.safety import MAX_RECOVER_SPEED_SHARE

    ap = argparse.ArgumentParser(
        prog="covey eval", description="Evaluate the guidance policy and baselines."
    )
    add_config_flags(
        ap,
        EvalConfig,
        types={
            "dt_s": finite("seconds"),
            "policy_period_s": finite("seconds", inclusive=True),
            "policy_separation_m": finite("metres"),
            "sigma_k": finite("standard deviations", inclusive=True),
            "recover_speed_share": finite(
                "shares of the speed limit", inclusive=True, maximum=MAX_RECOVER_SPEED_SHARE
            ),
            "tracking_lag_s": finite("seconds", inclusive=True),
        },
    )
    ap.add_argument("--merge", default="", help="comma list of results.json to combine into --out")
    renamed(
        ap,
        {
            "--dt": "--dt-s",
            "--policy-period": "--policy-period-s",
            "--policy-separation": "--policy-separation-m",
        },
    )
    return ap


def cli(argv=None, extra_controllers: Mapping[str, ControllerFactory] | None = None) -> dict:
    """`covey eval [--quick] [--out DIR] [--weights W] [--paper-weights W] [--occupancy CKPT]`.
    `extra_controllers`: see `controllers` (named with --controllers)."""
    from cli.options import config_from_flags, given

    ap = parser()
    a = ap.parse_args(argv)
    runs = [f.name for f in dataclasses.fields(EvalConfig) if f.name != "out"]
    if a.merge and (flags := given(ap, a, *runs)):
        ap.error(f"{', '.join(flags)}: --merge combines results files and runs nothing")
    if a.merge:
        result = merge([p for p in a.merge.split(",") if p], a.out)
        print(markdown(result["summary"]))
        return result
    if not set(a.links) <= {"perfect", "degraded"}:
        ap.error(f"--links takes perfect and/or degraded, got {','.join(a.links)!r}")
    try:
        VehicleModel.named(a.vehicles)
    except ValueError as e:
        ap.error(f"--vehicles: {e}")
    if not set(a.suites) <= {"circle", "conflict", "large", "intruder", "manned", "zones"}:
        ap.error(
            "--suites takes circle, conflict, large, intruder, manned, zones, "
            f"got {','.join(a.suites)!r}"
        )
    cfg = config_from_flags(EvalConfig, a)
    result = main(cfg, extra_controllers)
    print(markdown(result["summary"]))
    return result


if __name__ == "__main__":
    cli()
