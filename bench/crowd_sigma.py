"""Dense crowds on plain GNSS: true-position collisions and extra time against the filter's
confidence factor sigma_k (policy.safety.SafetyConfig.sigma_k).

    python -m bench.crowd_sigma [--quick] [--seeds 12] [--sigma-k 3,3.5,4,5]
    # bench/results/crowd_sigma.json, bench/results/crowd_sigma.png (docs/bench_crowd_sigma.png)

Antipodal circles of 16, 32 and 50 (policy.scenarios.antipodal_circle: every vehicle through
the centre), policy + filter as `covey eval` flies it, on the perfect and the 3 Hz lossy link,
with realistic vehicles (`--vehicles realistic`: 0.3 s lag, 2.5 m/s^2, 0.2 m/s gusts, GNSS
estimates drifting 0.5 m), judged on true positions; the same cases with ideal vehicles give
the extra time the realistic figures are compared with. Each seed draws its own noise and
losses; every k flies the same seeds. A circle's centre is where a crowd cannot hold the
inflated berth (3.6 m + k sqrt(2) sigma between estimates): it compresses, and how much berth
is left above 3 m between true positions is what k buys.

What it costs beyond time: the 9 m gap of `covey eval --suites zones` (policy.scenarios
`zone_scenes`, three vehicles one way through a gap of three separations and two the other),
flown the same way over the same seeds: a wider berth and zone clearance leave less room at the
gap's mouth, and runs where a vehicle did not arrive in time are counted.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from bench import common

CIRCLES = (16, 32, 50)
LINKS = ("perfect", "degraded")


def _controller(
    vehicles: str, sigma_k: float, seed: int, suite: str, recover_speed_share: float | None = None
):
    """policy+filter as `covey eval --vehicles V --sigma-k K --suites S` flies it (with
    `--recover-speed-share` when given)."""
    from policy import eval as ev

    cfg = ev.EvalConfig(
        vehicles=vehicles,
        seed=seed,
        sigma_k=sigma_k,
        recover_speed_share=recover_speed_share,
        controllers=("policy+filter",),
        figures=False,
        progress=False,
        suites=(suite,),
    )
    return ev.controllers(cfg)["policy+filter"]


def _fly(
    vehicles: str,
    sigma_k: float,
    seed: int,
    circles,
    links,
    recover_speed_share: float | None = None,
) -> list[dict]:
    from policy import evalsim, scenarios
    from policy.pointmass import VehicleModel

    ctrl = _controller(vehicles, sigma_k, seed, "circle", recover_speed_share)
    model = VehicleModel.named(vehicles)
    link_cfg = {"perfect": evalsim.PERFECT, "degraded": evalsim.DEGRADED}
    rows = []
    for n in circles:
        starts, goals = scenarios.antipodal_circle(n)
        for li, link in enumerate(links):
            ctrl.reset()
            rng = np.random.default_rng([seed, n, li])
            r = evalsim.run(
                starts, goals, ctrl, link_cfg[link], evalsim.EvalSimConfig(vehicles=model), rng
            )
            rows.append(
                {
                    "vehicles": vehicles,
                    "sigma_k": sigma_k,
                    "seed": seed,
                    "n": n,
                    "link": link,
                    **{k: r[k] for k in ("collisions", "timeouts", "min_sep", "est_min_sep")},
                    "extra_time": r["extra_time"],
                }
            )
    return rows


def _fly_gap(sigma_k: float, seed: int, links) -> list[dict]:
    from policy import evalsim, scenarios, zone_eval
    from policy.pointmass import VehicleModel

    ctrl = _controller("realistic", sigma_k, seed, "zones")
    scenes = {name: rest for name, *rest in scenarios.zone_scenes(np.random.default_rng(0))}
    starts, goals, zones_m = scenes["gap-9m"]
    link_cfg = {"perfect": evalsim.PERFECT, "degraded": evalsim.DEGRADED}
    sim_cfg = evalsim.EvalSimConfig(vehicles=VehicleModel.named("realistic"))
    rows = []
    for li, link in enumerate(links):
        ctrl.reset()
        rng = np.random.default_rng([seed, 9, li])
        r = zone_eval.run(
            "policy+filter", starts, goals, zones_m, ctrl, link_cfg[link], sim_cfg, rng
        )
        rows.append(
            {
                "sigma_k": sigma_k,
                "seed": seed,
                "link": link,
                **{k: r[k] for k in ("timeouts", "arrived", "zone_entries", "min_zone_m")},
                "min_sep": r["min_sep"],
            }
        )
    return rows


def summarise_gap(rows: list[dict]) -> dict:
    return {
        "runs": len(rows),
        "runs_with_a_late_vehicle": sum(r["timeouts"] > 0 for r in rows),
        "late_vehicles": sum(r["timeouts"] for r in rows),
        "zone_entries": sum(r["zone_entries"] for r in rows),
        "closest_to_a_zone_m": min(r["min_zone_m"] for r in rows),
        "closest_true_m": min(r["min_sep"] for r in rows if r["min_sep"] is not None),
    }


def summarise(rows: list[dict], ideal: dict) -> dict:
    """One k's runs: collision cases, closest true approach, timeouts, extra time and its ratio
    to the ideal vehicles' in the same case (median over cases)."""
    ratios = [
        r["extra_time"] / ideal[(r["seed"], r["n"], r["link"])]
        for r in rows
        if r["extra_time"] and ideal.get((r["seed"], r["n"], r["link"]))
    ]
    seps = [r["min_sep"] for r in rows]
    return {
        "cases": len(rows),
        "collision_cases": sum(r["collisions"] > 0 for r in rows),
        "timeouts_vehicles": sum(r["timeouts"] for r in rows),
        "closest_true_m": min(seps),
        "median_closest_true_m": statistics.median(seps),
        "median_closest_estimated_m": statistics.median(r["est_min_sep"] for r in rows),
        "median_extra_time": statistics.median(r["extra_time"] for r in rows if r["extra_time"]),
        "median_over_ideal": statistics.median(ratios) if ratios else None,
    }


def by_k(summary: dict) -> list[dict]:
    """One flat row per k (what SUMMARY.md's table shows)."""
    return [
        {
            "sigma_k": float(k),
            "collision_cases": s["collision_cases"],
            "cases": s["cases"],
            "closest_true_m": s["closest_true_m"],
            "vehicles_late": s["timeouts_vehicles"],
            "extra_time_over_ideal": s["median_over_ideal"],
            "gap_runs_late": s["gap"]["runs_with_a_late_vehicle"] if "gap" in s else None,
            "gap_runs": s["gap"]["runs"] if "gap" in s else None,
        }
        for k, s in summary.items()
    ]


def plot(ks, summary: dict) -> None:
    plt = common.pyplot()
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(14, 3.8))
    cases = [summary[str(k)]["collision_cases"] for k in ks]
    bars = a.bar([str(k) for k in ks], cases, color="tab:red")
    for bar, k in zip(bars, ks, strict=True):
        a.annotate(
            f"{summary[str(k)]['timeouts_vehicles']} timed out",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    a.set_xlabel("sigma_k")
    a.set_ylabel(f"collision cases (of {summary[str(ks[0])]['cases']})")
    a.set_title("true positions < 3 m, circles of 16/32/50")
    b.plot(
        ks,
        [summary[str(k)]["median_over_ideal"] for k in ks],
        "o-",
        label="extra time / ideal (median)",
    )
    b.plot(
        ks,
        [summary[str(k)]["closest_true_m"] / 3.0 for k in ks],
        "s--",
        label="closest true / 3 m (min)",
    )
    b.axhline(1.0, color="grey", lw=0.8)
    b.set_xlabel("sigma_k")
    b.legend()
    b.set_title("what k costs and buys")
    if all("gap" in summary[str(k)] for k in ks):
        late = [summary[str(k)]["gap"]["runs_with_a_late_vehicle"] for k in ks]
        c.bar([str(k) for k in ks], late, color="tab:orange")
        c.set_ylabel(f"runs with a vehicle late (of {summary[str(ks[0])]['gap']['runs']})")
        c.set_title("the 9 m gap, two ways (zones suite)")
        c.set_xlabel("sigma_k")
    fig.tight_layout()
    common.save_figure(fig, "crowd_sigma")


def regap(sigma_ks=None) -> dict:
    """Re-fly the 9 m gap only, keeping the circles of the last full run (bench/results/
    crowd_sigma.json; circles fly no zones, so a change of the routes leaves them as they
    were): its seeds and factors, or `sigma_ks` of them."""
    import json

    path = common.out_dir() / "crowd_sigma.json"
    if not path.exists():
        raise SystemExit(f"--only-gap needs a full run's {path}; run without it first")
    result = json.loads(path.read_text())
    for key in ("section", "machine"):  # written afresh
        result.pop(key, None)
    ks = [k for k in result["sigma_ks"] if sigma_ks is None or k in sigma_ks]
    seeds, summary = result["seeds"], result["summary"]
    t0 = time.monotonic()
    gaps = [r for r in result["gap_runs"] if r["sigma_k"] not in ks]
    for k in ks:
        gap = [r for s in range(1, seeds + 1) for r in _fly_gap(k, s, LINKS)]
        gaps += gap
        summary[str(k)]["gap"] = summarise_gap(gap)
        common.say(f"sigma_k {k:g}: 9 m gap {summary[str(k)]['gap']}")
    result.update(by_k=by_k(summary), gap_runs=gaps, gap_wall_s=round(time.monotonic() - t0, 1))
    common.write_json("crowd_sigma", result)
    plot(result["sigma_ks"], summary)
    return result


def main(quick: bool = False, seeds: int = 12, sigma_ks=(3.0, 3.5, 4.0, 5.0)) -> dict:
    circles = (16,) if quick else CIRCLES
    if quick:
        seeds, sigma_ks = 2, (3.0, 4.0)
    t0 = time.monotonic()
    ideal_rows = [r for s in range(1, seeds + 1) for r in _fly("ideal", 3.0, s, circles, LINKS)]
    ideal = {(r["seed"], r["n"], r["link"]): r["extra_time"] for r in ideal_rows}
    runs, gaps, summary = list(ideal_rows), [], {}
    for k in sigma_ks:
        rows = []
        for s in range(1, seeds + 1):
            rows += _fly("realistic", k, s, circles, LINKS)
            common.say(f"sigma_k {k:g}: seed {s}/{seeds} ({time.monotonic() - t0:.0f} s)")
        runs += rows
        summary[str(k)] = summarise(rows, ideal)
        gap = [r for s in range(1, seeds + 1) for r in _fly_gap(k, s, LINKS)]
        gaps += gap
        summary[str(k)]["gap"] = summarise_gap(gap)
        common.say(f"sigma_k {k:g}: {summary[str(k)]}")
    result = {
        "by_k": by_k(summary),
        "circles": list(circles),
        "links": list(LINKS),
        "seeds": seeds,
        "sigma_ks": list(sigma_ks),
        "ideal_median_extra_time": statistics.median(v for v in ideal.values() if v),
        "summary": summary,
        "runs": runs,
        "gap_runs": gaps,
        "wall_s": round(time.monotonic() - t0, 1),
    }
    common.write_json("crowd_sigma", result)
    plot(list(sigma_ks), summary)
    for k in sigma_ks:
        s = summary[str(k)]
        print(
            f"sigma_k {k:g}: {s['collision_cases']}/{s['cases']} collision cases, closest "
            f"{s['closest_true_m']:.2f} m true (median {s['median_closest_true_m']:.2f}), "
            f"{s['timeouts_vehicles']} vehicles timed out, extra time {s['median_extra_time']:.2f} "
            f"({s['median_over_ideal']:.2f}x ideal); 9 m gap: {s['gap']['runs_with_a_late_vehicle']}"
            f"/{s['gap']['runs']} runs with a vehicle late, {s['gap']['zone_entries']} zone entries"
        )
    return result


if __name__ == "__main__":
    from cli.options import finite

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one circle, 2 seeds, k 3 and 4")
    ap.add_argument("--seeds", type=int, default=12, help="seeds 1..N (default 12)")
    ap.add_argument(
        "--only-gap",
        action="store_true",
        help="re-fly the 9 m gap alone, keeping the last full run's circles (after a routing change)",
    )
    ap.add_argument(
        "--sigma-k",
        default="3,3.5,4,5",
        help="comma list of confidence factors to compare (default 3,3.5,4,5)",
    )
    a = ap.parse_args()
    try:
        ks = tuple(finite("standard deviations", inclusive=True)(x) for x in a.sigma_k.split(","))
    except argparse.ArgumentTypeError as e:
        ap.error(f"--sigma-k: {e}")
    if a.seeds < 1:
        ap.error(f"--seeds must be at least 1, got {a.seeds}")
    if a.only_gap:
        regap(ks)
    else:
        main(quick=a.quick, seeds=a.seeds, sigma_ks=ks)
