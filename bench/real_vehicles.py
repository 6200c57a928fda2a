"""Realistic vehicles in `covey eval`: collisions and closest approach on TRUE positions.

    python -m bench.real_vehicles [--quick] [--seed 7] [--reuse DIR]
    # table; bench/results/real_vehicles.{json,png}, docs/bench_real_vehicles.png

Every suite (circles, forced conflicts, large swarms), both links (perfect; 3 Hz, 20 % loss,
100 ms), policy+filter (numpy), c+filter (the C core as onboard) and ORCA, flown four ways:
  - ideal: vehicles fly the command exactly and know where they are (today's figures);
  - realistic k0: policy.pointmass.VehicleModel.realistic() (0.3 s lag, 2.5 m/s^2, 0.2 m/s
    gusts over 5 s, GNSS estimates drifting 0.5 m over 10 s), the filter taking the estimates
    as the truth (sigma_k 0: before issue 35);
  - realistic k3: the filter inflating each pair by 3 sqrt(si^2 + sj^2) (the first default);
  - realistic k4: by 4 sqrt(si^2 + sj^2), policy.safety SIGMA_K since dense circles on fresh
    seeds showed k3 short (bench/crowd_sigma.py). (Telling the policy the inflation,
    --tell-inflation, was a fifth variant until then: docs/policy.md has its numbers.)
Collisions (a pair under 3 m) and the closest approach are judged on the true positions;
est_min_sep is the closest approach of the estimates. Extra time is against the ideal run of
the same controller, link and suite. `--reuse DIR`: read DIR/<variant>/results.json of runs
made with `covey eval` instead of flying (the variants' flags are in VARIANTS).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench import common

VARIANTS = {
    "ideal": {"vehicles": "ideal"},
    "realistic-k0": {"vehicles": "realistic", "sigma_k": 0.0},
    "realistic-k3": {"vehicles": "realistic", "sigma_k": 3.0},
    "realistic-k4": {"vehicles": "realistic", "sigma_k": 4.0},
}
CONTROLLERS = ("policy+filter", "c+filter", "orca")


def fly(variant: str, seed: int, quick: bool, out: Path) -> dict:
    """One `covey eval` run of a variant (with the C core)."""
    from firmware import ceval
    from policy.eval import EvalConfig

    cfg = EvalConfig(
        out=str(out / variant),
        seed=seed,
        quick=quick,
        figures=False,
        progress=False,
        controllers=CONTROLLERS,
        **VARIANTS[variant],
    )
    return ceval.main(cfg)


def table(results: dict[str, dict]) -> list[dict]:
    """One row per (variant, controller, link, suite) with the extra time against ideal."""
    ideal = {(s["controller"], s["link"], s["suite"]): s for s in results["ideal"]["summary"]}
    rows = []
    for variant, res in results.items():
        for s in res["summary"]:
            base = ideal.get((s["controller"], s["link"], s["suite"]))
            ratio = None
            if base and base["extra_time"] and s["extra_time"]:
                ratio = s["extra_time"] / base["extra_time"]
            rows.append(
                {
                    "variant": variant,
                    "controller": s["controller"],
                    "link": s["link"],
                    "suite": s["suite"],
                    "cases": s["cases"],
                    "success": s["success"],
                    "collision_cases": s.get("collision_cases"),
                    "collisions": s["collisions"],
                    "min_sep_true_m": s["min_sep"],
                    "min_sep_est_m": s.get("est_min_sep"),
                    "extra_time": s["extra_time"],
                    "extra_time_vs_ideal": ratio,
                }
            )
    return rows


def plot(results: dict[str, dict]) -> None:
    """The closest true approach of every run (case x link), per variant: ideal vs realistic."""
    plt = common.pyplot()
    fig, axes = plt.subplots(1, len(CONTROLLERS), figsize=(4.2 * len(CONTROLLERS), 3.6))
    axes = np.atleast_1d(axes)
    colors = {
        "ideal": "C0",
        "realistic-k0": "C3",
        "realistic-k3": "C2",
        "realistic-k4": "C1",
    }
    bins = np.linspace(2.0, 8.0, 49)
    for ax, ctrl in zip(axes, CONTROLLERS, strict=True):
        for variant, res in results.items():
            seps = [r["min_sep"] for r in res["runs"] if r["controller"] == ctrl and r["min_sep"]]
            if seps:
                ax.hist(
                    np.clip(seps, bins[0], bins[-1]),
                    bins=bins,
                    histtype="step",
                    color=colors.get(variant, "k"),
                    label=f"{variant} (min {min(seps):.2f} m)",
                )
        ax.axvline(3.0, color="k", lw=1, ls=":")
        ax.set_title(ctrl)
        ax.set_xlabel("closest TRUE approach of a run (m)")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("runs (case x link)")
    fig.suptitle("covey eval: closest true approach, ideal vs realistic vehicles (3 m separation)")
    fig.tight_layout()
    common.save_figure(fig, "real_vehicles")


def main(seed: int = 7, quick: bool = False, reuse: str | None = None) -> dict:
    results = {}
    work = Path(reuse) if reuse else common.out_dir() / "real_vehicles_runs"
    for variant in VARIANTS:
        path = work / variant / "results.json"
        if reuse:
            if not path.is_file():
                common.say(f"{variant}: no {path}, left out")
                continue
            results[variant] = json.loads(path.read_text())
        else:
            common.say(f"{variant}: covey eval, seed {seed}")
            results[variant] = fly(variant, seed, quick, work)
    rows = table(results)
    plot(results)
    print(
        "variant            controller     link      suite     coll.cases  true min  est min  extra  vs ideal"
    )
    for r in rows:
        ratio = "-" if r["extra_time_vs_ideal"] is None else f"{r['extra_time_vs_ideal']:.3f}"
        print(
            f"{r['variant']:18s} {r['controller']:14s} {r['link']:9s} {r['suite']:9s} "
            f"{r['collision_cases']}/{r['cases']:<8} {r['min_sep_true_m'] or 0:.2f}     "
            f"{r['min_sep_est_m'] or 0:.2f}    {r['extra_time'] or 0:.3f}  {ratio}"
        )
    return {"seed": seed, "quick": quick, "variants": VARIANTS, "rows": rows}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="covey eval's smoke suites")
    ap.add_argument("--seed", type=int, default=7, help="scenario and noise seed (default 7)")
    ap.add_argument("--reuse", default=None, help="read DIR/<variant>/results.json instead")
    args = ap.parse_args()
    common.write_json("real_vehicles", main(args.seed, args.quick, args.reuse))
