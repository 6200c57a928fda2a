"""Vehicles unlike the `realistic` preset, on fresh seeds: does anything collide?

    python -m bench.off_preset [--jobs 2] [--suites circle,conflict,large,intruder]
    # table; bench/results/off_preset.json, docs/bench_off_preset.png

`covey eval --vehicles SPEC --seed N` for each (SPEC, N) of `MODELS` (or `--models
'SPEC@N;SPEC@N'`): heavier gusts and a slower loop, a GNSS error that changes fast or slowly,
a weaker acceleration, GNSS a little worse than the preset; policy+filter and c+filter, both
links. Collisions and the closest approach are on true positions; "late" counts vehicles that
did not arrive in time. docs/sky.md "Off-preset spot checks" quotes it.
"""

from __future__ import annotations

import argparse
import concurrent.futures

from bench import common

MODELS: tuple[tuple[str, int], ...] = (
    ("realistic:gust_m_s=0.35,lag_s=0.45", 1201),
    ("realistic:drift_corr_s=2", 1202),
    ("realistic:max_accel_m_s2=1.5,lag_s=0.5", 1203),
    ("realistic:drift_m=0.6,gust_m_s=0.3", 1204),
    ("realistic:drift_corr_s=30,drift_m=0.7", 1205),
)
"""(vehicle model, seed) pairs flown by default: each model on a seed of its own."""
CONTROLLERS = ("policy+filter", "c+filter")
SUITES = ("circle", "conflict", "large", "intruder")


def fly(spec: str, seed: int, suites: tuple[str, ...], out: str) -> dict:
    """One `covey eval` run (with the C core); its per-run rows."""
    res = common.covey_eval(out, seed, spec, suites, CONTROLLERS)
    return {"vehicles": spec, "seed": seed, "runs": res["runs"]}


def total(flown: dict) -> dict:
    """One model's row: runs, collision cases, closest true approach (to anyone, and to an
    intruder), late vehicles of all covey vehicles, median extra time."""
    runs = flown["runs"]
    extra = sorted(r["extra_time"] for r in runs if r.get("extra_time") is not None)
    intruder = [r["intruder_min_sep"] for r in runs if r.get("intruder_min_sep") is not None]
    return {
        "vehicles": flown["vehicles"],
        "seed": flown["seed"],
        "runs": len(runs),
        "collision_cases": sum(1 for r in runs if r["collisions"] > 0),
        "min_sep_true_m": min(r["min_sep"] for r in runs),
        "intruder_min_sep_m": min(intruder) if intruder else None,
        "late_vehicles": sum(r["n"] - r["arrived"] for r in runs),
        "covey_vehicles": sum(r["n"] for r in runs),
        "extra_time_median": extra[len(extra) // 2] if extra else None,
    }


def plot(rows: list[dict]) -> None:
    """The closest true approach and the late vehicles, one bar each model."""
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12.0, 3.8))
    names = [
        r["vehicles"].removeprefix("realistic:").replace(",", "\n") + f"\nseed {r['seed']}"
        for r in rows
    ]
    x = range(len(rows))
    axes[0].bar(x, [r["min_sep_true_m"] for r in rows], color="C0")
    axes[0].axhline(3.0, color="C3", lw=1.0, label="3 m: a collision")
    axes[0].set_ylabel("closest true approach (m)")
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [r["late_vehicles"] for r in rows], color="C1")
    axes[1].set_ylabel("vehicles late")
    for ax in axes:
        ax.set_xticks(list(x), names, fontsize=7)
    fig.suptitle("realistic vehicles off the preset, fresh seeds (policy+filter and c+filter)")
    fig.tight_layout()
    common.save_figure(fig, "off_preset")


def table(rows: list[dict]) -> str:
    lines = ["vehicles                                 seed  runs  coll.  closest  intruder  late"]
    for r in rows:
        intruder = "-" if r["intruder_min_sep_m"] is None else f"{r['intruder_min_sep_m']:.2f}"
        lines.append(
            f"{r['vehicles']:40s} {r['seed']:<5d} {r['runs']:<5d} {r['collision_cases']:<6d} "
            f"{r['min_sep_true_m']:<8.2f} {intruder:9s} {r['late_vehicles']}/{r['covey_vehicles']}"
        )
    return "\n".join(lines)


def models_arg(text: str) -> tuple[tuple[str, int], ...]:
    """argparse `type` of --models: 'SPEC@SEED;SPEC@SEED' (a spec has commas of its own)."""
    out = []
    for item in (x.strip() for x in text.split(";") if x.strip()):
        spec, at, seed = item.rpartition("@")
        if not at or not spec:
            raise argparse.ArgumentTypeError(f"{item!r} is not SPEC@SEED")
        try:
            out.append((spec, int(seed)))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{item!r}: the seed must be an integer") from None
    if not out:
        raise argparse.ArgumentTypeError("no SPEC@SEED given")
    return tuple(out)


def main(models=MODELS, suites=SUITES, jobs: int = 2) -> dict:
    from policy.pointmass import VehicleModel

    for spec, _ in models:
        VehicleModel.named(spec)  # a bad spec is refused here, saying why, before any flight
    work = common.REPO / "runs" / "off_preset"  # gitignored: every run's results.json
    tasks = [(spec, seed, tuple(suites), str(work / f"{seed}")) for spec, seed in models]
    flown = []
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(fly, *t): t for t in tasks}
        for i, f in enumerate(concurrent.futures.as_completed(futures), 1):
            flown.append(f.result())
            spec, seed, *_ = futures[f]
            common.say(f"[{i}/{len(tasks)}] {spec}, seed {seed}: done")
    order = {m: i for i, m in enumerate(models)}
    rows = sorted((total(f) for f in flown), key=lambda r: order[(r["vehicles"], r["seed"])])
    plot(rows)
    print(table(rows))
    result = {"suites": list(suites), "controllers": list(CONTROLLERS), "rows": rows}
    common.write_json("off_preset", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=models_arg, default=MODELS, help="'SPEC@SEED;SPEC@SEED'")
    ap.add_argument("--suites", default=",".join(SUITES), help="covey eval suites (comma list)")
    ap.add_argument("--jobs", type=int, default=2, help="evaluations at once")
    a = ap.parse_args()
    if a.jobs < 1:
        ap.error("--jobs must be at least 1")
    suites = tuple(s for s in a.suites.split(",") if s)
    try:
        main(a.models, suites, a.jobs)
    except ValueError as exc:
        ap.error(str(exc))
