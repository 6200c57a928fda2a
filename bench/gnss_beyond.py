"""GNSS worse than the preset: covey as shipped against the berth told before and RVO2's parting.

    python -m bench.gnss_beyond [--sigmas-m 0.5,0.75,1.0] [--seeds 781,782] [--jobs 2]
                                [--ways shipped,told-1.25,part-within-dt]
    # table; bench/results/gnss_beyond.json, docs/bench_gnss_beyond.png

`covey eval --vehicles realistic:drift_m=S` (0.3 s lag, 2.5 m/s^2, 0.2 m/s gusts, estimates
drifting S m), the circle, conflict and large suites, both links, policy+filter and c+filter,
flown in up to three ways on the same seeds:
  - shipped: beyond 0.5 m the network's told separation grows by told_scale
    (policy/runtime.py TOLD_SIGMA_FREE_M), and a pair found inside its distance parts at up to
    the vehicles' full speed (policy/safety.py RECOVER_SPEED_SHARE);
  - told-1.25: `--policy-separation-m 1.25`, the berth told before, whatever the sigma (at or
    below 0.5 m the same flight as shipped: tests/test_told_scale.py);
  - part-within-dt: `--recover-speed-share 0`, the filter asks such a pair to part within one
    control period, as RVO2 does (before). Collisions (a pair
under 3 m) and the closest approach are on true positions; "late" counts vehicles that did not
arrive in time (timeouts).
"""

from __future__ import annotations

import argparse
import concurrent.futures

import numpy as np

from bench import common

WAYS: dict[str, dict] = {
    "shipped": {},
    "told-1.25": {"policy_separation_m": 1.25},
    "part-within-dt": {"recover_speed_share": 0.0},
}
"""Way -> the EvalConfig fields it changes."""
CONTROLLERS = ("policy+filter", "c+filter")
SUITES = ("circle", "conflict", "large")


def fly(way: str, sigma_m: float, seed: int, out: str) -> dict:
    """One `covey eval` run (with the C core); its summary rows."""
    vehicles = f"realistic:drift_m={sigma_m}"
    res = common.covey_eval(out, seed, vehicles, SUITES, CONTROLLERS, **WAYS[way])
    return {"way": way, "sigma_m": sigma_m, "seed": seed, "summary": res["summary"]}


def totals(runs: list[dict]) -> list[dict]:
    """Per (way, sigma, controller): collision cases, cases, late vehicles, closest true
    approach and the median extra time, over seeds, links and suites."""
    out = []
    keys = sorted({(r["way"], r["sigma_m"], s["controller"]) for r in runs for s in r["summary"]})
    for way, sigma, ctrl in keys:
        rows = [
            s
            for r in runs
            if r["way"] == way and r["sigma_m"] == sigma
            for s in r["summary"]
            if s["controller"] == ctrl
        ]
        extra = [s["extra_time"] for s in rows if s["extra_time"]]
        out.append(
            {
                "way": way,
                "sigma_m": sigma,
                "controller": ctrl,
                "cases": sum(s["cases"] for s in rows),
                "collision_cases": sum(s["collision_cases"] for s in rows),
                "late_vehicles": sum(s["timeouts"] for s in rows),
                "vehicles": sum(s["vehicles"] for s in rows),
                "min_sep_true_m": min(s["min_sep"] for s in rows),
                "extra_time_median": float(np.median(extra)) if extra else None,
            }
        )
    return out


def plot(rows: list[dict]) -> None:
    """Late vehicles, collision cases and the closest true approach against sigma, each way."""
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13.0, 3.8))
    colours = dict(zip(WAYS, ("C0", "C3", "C2"), strict=True))
    for way, ctrl in [(w, c) for w in WAYS for c in CONTROLLERS]:
        style = colours[way] + ("-o" if ctrl == CONTROLLERS[0] else "--s")
        mine = sorted((r for r in rows if r["way"] == way and r["controller"] == ctrl),
                      key=lambda r: r["sigma_m"])  # fmt: skip
        if not mine:
            continue
        x = [r["sigma_m"] for r in mine]
        axes[0].plot(x, [r["late_vehicles"] for r in mine], style, label=f"{way}, {ctrl}")
        axes[1].plot(x, [r["collision_cases"] for r in mine], style, label=f"{way}, {ctrl}")
        axes[2].plot(x, [r["min_sep_true_m"] for r in mine], style, label=f"{way}, {ctrl}")
    axes[0].set_ylabel(f"vehicles late (of {mine[0]['vehicles'] if mine else '?'})")
    axes[1].set_ylabel("collision cases (true < 3 m)")
    axes[2].set_ylabel("closest true approach (m)")
    axes[2].axhline(3.0, color="grey", lw=0.8)
    for ax in axes:
        ax.set_xlabel("GNSS drift 1-sigma (m)")
    axes[0].legend(fontsize=7)
    fig.suptitle("covey eval with GNSS at and beyond the 0.5 m preset: as shipped and as before")
    fig.tight_layout()
    common.save_figure(fig, "gnss_beyond")


def main(sigmas_m: list[float], seeds: list[int], jobs: int, ways: list[str]) -> dict:
    work = common.REPO / "runs" / "gnss_beyond"  # gitignored: every run's results.json
    tasks = [
        (way, s, seed, str(work / f"{way}_{s}_{seed}"))
        for s in sigmas_m
        for seed in seeds
        for way in ways
    ]
    runs = []
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(fly, *t): t for t in tasks}
        for i, f in enumerate(concurrent.futures.as_completed(futures), 1):
            runs.append(f.result())
            way, s, seed, _ = futures[f]
            common.say(f"[{i}/{len(tasks)}] {way}, sigma {s} m, seed {seed}: done")
    rows = totals(runs)
    plot(rows)
    print(
        "way             sigma  controller     coll.cases  late/vehicles  true min  extra (median)"
    )
    for r in rows:
        print(
            f"{r['way']:15s} {r['sigma_m']:<5g}  {r['controller']:14s} "
            f"{r['collision_cases']}/{r['cases']:<9} {r['late_vehicles']}/{r['vehicles']:<10} "
            f"{r['min_sep_true_m']:.2f}      {r['extra_time_median'] or 0:.3f}"
        )
    ways_run = {w: WAYS[w] for w in ways}
    return {"sigmas_m": sigmas_m, "seeds": seeds, "ways": ways_run, "rows": rows, "runs": runs}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sigmas-m", default="0.5,0.75,1.0", help="GNSS drift 1-sigmas (comma list)")
    ap.add_argument("--seeds", default="781,782", help="scenario and noise seeds (comma list)")
    ap.add_argument("--jobs", type=int, default=2, help="evaluations at once")
    ap.add_argument("--ways", default=",".join(WAYS), help=f"comma list of {', '.join(WAYS)}")
    a = ap.parse_args()
    ways = [w for w in a.ways.split(",") if w]
    unknown = [w for w in ways if w not in WAYS]
    if unknown or not ways:
        raise SystemExit(f"--ways: {', '.join(unknown) or 'none'} not among {', '.join(WAYS)}")
    sig = [float(x) for x in a.sigmas_m.split(",")]
    seeds = [int(x) for x in a.seeds.split(",")]
    if not sig or any(not (s > 0) for s in sig) or a.jobs < 1:
        raise SystemExit("--sigmas-m must be positive numbers and --jobs at least 1")
    common.write_json("gnss_beyond", main(sig, seeds, a.jobs, ways))
