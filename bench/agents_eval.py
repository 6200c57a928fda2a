"""As the agents fly: `covey eval --controllers agents` (every vehicle flies the agents' own
guidance tick: agent/eval_agents.py) on every suite (circles, forced conflicts, swarms of 35 and
100, intruders at 1x-2x, manned aircraft at 20-60 m/s, keep-out zones), both links, ideal and
realistic vehicles, fresh seeds. Collisions and the closest approach are on true positions.

    python -m bench.agents_eval [--quick] [--seeds 71,73] [--workers 2] [--replot]
    # bench/results/agents_eval.json, docs/bench_agents_eval.png

Each (vehicles, seed) is one `covey eval` run in its own process (`--workers` at once).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor

from bench import common

SUITES = ("circle", "conflict", "large", "intruder", "manned", "zones")
SEEDS = (71, 73)
VEHICLES = ("ideal", "realistic")


def one(vehicles: str, seed: int, suites: tuple, quick: bool) -> list[dict]:
    """One `covey eval` with the agents' controller: a row per (suite, link)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import policy.eval as ev
    from agent.eval_agents import CONTROLLERS

    with tempfile.TemporaryDirectory() as out:
        cfg = ev.EvalConfig(
            out=out,
            seed=seed,
            suites=suites,
            vehicles=vehicles,
            quick=quick,
            figures=False,
            progress=False,
            controllers=("agents",),
        )
        runs = ev.main(cfg, CONTROLLERS)["runs"]
    rows = []
    for suite in suites:
        for link in cfg.links:
            rs = [r for r in runs if r["suite"] == suite and r["link"] == link]
            if not rs:
                continue
            rows.append(
                {
                    "vehicles": vehicles,
                    "seed": seed,
                    "suite": suite,
                    "link": link,
                    "runs": len(rs),
                    "collision_cases": sum(bool(r["collisions"]) for r in rs),
                    "closest_true_m": min(r["min_sep"] for r in rs if r["min_sep"] is not None),
                    "success": sum(r["success"] for r in rs) / len(rs),
                    "timeouts": sum(r["timeouts"] for r in rs),
                    "extra_time_median": common.pct(
                        [r["extra_time"] for r in rs if r["extra_time"] is not None], 50
                    ),
                    "manned_entries": sum(r.get("manned_entries", 0) for r in rs),
                    "zone_entries": sum(r.get("zone_entries", 0) for r in rs),
                }
            )
    return rows


def main(quick: bool = False, seeds=SEEDS, workers: int = 2) -> dict:
    suites = ("circle", "conflict", "intruder") if quick else SUITES
    seeds = seeds[:1] if quick else seeds
    jobs = [(v, s) for v in VEHICLES for s in seeds]
    rows: list[dict] = []
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        futures = {pool.submit(one, v, s, suites, quick): (v, s) for v, s in jobs}
        for fut, (v, s) in futures.items():
            got = fut.result()
            rows += got
            cases = sum(r["collision_cases"] for r in got)
            closest = min(r["closest_true_m"] for r in got)
            common.say(
                f"{v}, seed {s}: {sum(r['runs'] for r in got)} runs, {cases} collision cases, "
                f"closest {closest:.2f} m"
            )
    result: dict = {"quick": quick, "suites": list(suites), "seeds": list(seeds), "rows": rows}
    for v in VEHICLES:
        mine = [r for r in rows if r["vehicles"] == v]
        result[v] = {
            "runs": sum(r["runs"] for r in mine),
            "collision_cases": sum(r["collision_cases"] for r in mine),
            "closest_true_m": min(r["closest_true_m"] for r in mine),
            "success": sum(r["success"] * r["runs"] for r in mine) / sum(r["runs"] for r in mine),
            "manned_entries": sum(r["manned_entries"] for r in mine),
            "zone_entries": sum(r["zone_entries"] for r in mine),
        }
    common.write_json("agents_eval", result)
    plot(rows)
    return result


def plot(rows: list[dict]) -> None:
    """Closest true approach per suite, each (vehicles, link) a marker, every seed a point."""
    plt = common.pyplot()
    suites = list(dict.fromkeys(r["suite"] for r in rows))
    fig, ax = plt.subplots(figsize=(9, 4))
    styles = {
        ("ideal", "perfect"): ("o", "tab:blue"),
        ("ideal", "degraded"): ("s", "tab:cyan"),
        ("realistic", "perfect"): ("o", "tab:red"),
        ("realistic", "degraded"): ("s", "tab:orange"),
    }
    for (v, link), (marker, colour) in styles.items():
        mine = [r for r in rows if r["vehicles"] == v and r["link"] == link]
        offset = (list(styles).index((v, link)) - 1.5) * 0.12
        xs = [suites.index(r["suite"]) + offset for r in mine]
        ax.scatter(
            xs,
            [r["closest_true_m"] for r in mine],
            marker=marker,
            color=colour,
            label=f"{v}, {link}",
        )
    ax.axhline(3.0, color="k", lw=1, ls="--", label="3 m separation")
    ax.set_xticks(range(len(suites)), suites)
    ax.set_ylabel("closest true approach (m)")
    ax.set_title("covey eval --controllers agents: as the agents fly, every seed")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    common.save_figure(fig, "agents_eval")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--replot", action="store_true", help="only redraw the PNG from the JSON")
    a = ap.parse_args()
    if a.replot:
        import json

        plot(json.loads((common.out_dir() / "agents_eval.json").read_text())["rows"])
        raise SystemExit(0)
    res = main(a.quick, tuple(int(s) for s in a.seeds.split(",") if s), a.workers)
    for v in VEHICLES:
        print(v, res[v])
    for r in res["rows"]:
        print(
            f"{r['vehicles']:9s} seed {r['seed']:3d} {r['suite']:9s} {r['link']:8s} "
            f"{r['collision_cases']}/{r['runs']} closest {r['closest_true_m']:.2f} m "
            f"success {100 * r['success']:.0f} % extra {r['extra_time_median']:.2f}"
        )
