"""One-lane gaps with and without the rule of who goes first (policy/lanes.py).

    python -m bench.one_lane [--seeds 8] [--controllers policy+filter,c+filter]
    # bench/results/one_lane.json, docs/bench_one_lane.png

The two zone scenes of `covey eval --suites zones` where streams meet in a gap of three
separations (three vehicles one way, two the other): `gap-9m` (two 10 m blocks: a way round
exists, two-way routes take it) and `gate-9m` (a 9 m gate in a 120 m wall: no way round), flown
with realistic vehicles (0.5 m GNSS: the gap is one lane) on both links, seeds 1..N, with the
rule on (as shipped) and off, alternating. Counted per run: vehicles late (not arrived within
4x their straight-line time), zone entries and the closest true approach to a zone and between
vehicles; the extra time of the runs where all arrived.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from bench import common
from bench.crowd_sigma import LINKS, _controller

SCENES = ("gap-9m", "gate-9m")


def _fly(scene: str, controller: str, seed: int, lanes_on: bool) -> list[dict]:
    from policy import evalsim, scenarios, zone_eval
    from policy.lanes import LaneConfig
    from policy.pointmass import VehicleModel

    ctrl = _controller("realistic", 4.0, seed, "zones") if controller == "policy+filter" else None
    if ctrl is None:
        from firmware.ceval import CONTROLLERS
        from policy import eval as ev

        cfg = ev.EvalConfig(vehicles="realistic", seed=seed, controllers=(controller,))
        ctrl = ev.controllers(cfg, CONTROLLERS)[controller]
    scenes = {name: rest for name, *rest in scenarios.zone_scenes(np.random.default_rng(0))}
    starts, goals, zones_m = scenes[scene]
    link_cfg = {"perfect": evalsim.PERFECT, "degraded": evalsim.DEGRADED}
    sim_cfg = evalsim.EvalSimConfig(vehicles=VehicleModel.named("realistic"))
    rows = []
    for li, link in enumerate(LINKS):
        if hasattr(ctrl, "reset"):
            ctrl.reset()
        rng = np.random.default_rng([seed, 9, li])  # the same noise with the rule on and off
        r = zone_eval.run(
            controller,
            starts,
            goals,
            zones_m,
            ctrl,
            link_cfg[link],
            sim_cfg,
            rng,
            lanes=LaneConfig(enabled=lanes_on),
        )
        rows.append(
            {
                "scene": scene,
                "controller": controller,
                "lanes": lanes_on,
                "seed": seed,
                "link": link,
                **{k: r[k] for k in ("timeouts", "arrived", "zone_entries", "min_zone_m")},
                "min_sep": r["min_sep"],
                "extra_time": r["extra_time"] if r["timeouts"] == 0 else None,
            }
        )
    return rows


def summarise(rows: list[dict]) -> dict:
    done = [r["extra_time"] for r in rows if r["extra_time"] is not None]
    return {
        "runs": len(rows),
        "runs_with_a_late_vehicle": sum(r["timeouts"] > 0 for r in rows),
        "late_vehicles": sum(r["timeouts"] for r in rows),
        "vehicles": sum(r["timeouts"] + r["arrived"] for r in rows),
        "zone_entries": sum(r["zone_entries"] for r in rows),
        "closest_to_a_zone_m": round(min(r["min_zone_m"] for r in rows), 2),
        "closest_true_m": round(min(r["min_sep"] for r in rows if r["min_sep"] is not None), 2),
        "extra_time_median": round(statistics.median(done), 2) if done else None,
    }


def plot(summary: dict, controllers) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    labels, on, off = [], [], []
    for scene in SCENES:
        for c in controllers:
            labels.append(f"{scene}\n{c}")
            on.append(summary[f"{scene} {c} on"]["runs_with_a_late_vehicle"])
            off.append(summary[f"{scene} {c} off"]["runs_with_a_late_vehicle"])
    x = np.arange(len(labels))
    for bars in (
        ax.bar(x - 0.2, off, 0.4, label="rule off (before)", color="#c44"),
        ax.bar(x + 0.2, on, 0.4, label="rule on (shipped)", color="#4a4"),
    ):
        ax.bar_label(bars, fontsize=8)
    runs = summary[f"{SCENES[0]} {controllers[0]} on"]["runs"]
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel(f"runs with a vehicle late (of {runs})")
    ax.set_title("one-lane gaps, realistic vehicles, both links: who goes first")
    ax.legend()
    fig.tight_layout()
    fig.savefig(common.DOCS / "bench_one_lane.png", dpi=110)


def main(seeds: int = 8, controllers=("policy+filter", "c+filter")) -> dict:
    t0 = time.monotonic()
    rows: list[dict] = []
    for seed in range(1, seeds + 1):
        for scene in SCENES:
            for c in controllers:
                for on in (True, False):
                    got = _fly(scene, c, seed, on)
                    rows += got
                    late = sum(r["timeouts"] for r in got)
                    common.say(
                        f"seed {seed} {scene} {c} rule {'on ' if on else 'off'}: "
                        f"{late} late, zone entries {sum(r['zone_entries'] for r in got)}"
                    )
    summary = {
        f"{scene} {c} {'on' if on else 'off'}": summarise(
            [r for r in rows if r["scene"] == scene and r["controller"] == c and r["lanes"] == on]
        )
        for scene in SCENES
        for c in controllers
        for on in (True, False)
    }
    result = {
        "seeds": seeds,
        "summary": summary,
        "runs": rows,
        "wall_s": round(time.monotonic() - t0, 1),
        "machine": common.machine(),
    }
    common.write_json("one_lane", result)
    plot(summary, controllers)
    for k, s in summary.items():
        print(
            f"{k:28s} late in {s['runs_with_a_late_vehicle']}/{s['runs']} runs "
            f"({s['late_vehicles']} of {s['vehicles']} vehicles), entries {s['zone_entries']}, "
            f"closest to a zone {s['closest_to_a_zone_m']} m, pair {s['closest_true_m']} m, "
            f"extra time {s['extra_time_median']}"
        )
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8, help="seeds 1..N (default 8)")
    ap.add_argument("--controllers", default="policy+filter,c+filter")
    a = ap.parse_args()
    if a.seeds < 1:
        ap.error("--seeds must be at least 1")
    ctrls = tuple(a.controllers.split(","))
    if not ctrls or any(c not in ("policy+filter", "c+filter") for c in ctrls):
        ap.error(f"--controllers {a.controllers!r}: policy+filter and/or c+filter")
    main(a.seeds, ctrls)
