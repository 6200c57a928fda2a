"""What the filter's uncertainty padding costs by itself: vehicles that fly exactly but report
plain GNSS's 0.5 m, against ideal and realistic ones.

    python -m bench.berth_floor [--seeds 321,322] [--suites circle,conflict,zones]
                                [--variants ideal,padded,realistic] [--reuse]
    # table; bench/results/berth_floor.{json,png}, docs/bench_berth_floor.png

Issue 35 asks realistic vehicles (0.3 s lag, 2.5 m/s^2, 0.2 m/s gusts, 0.5 m GNSS drift) to take
at most 15 % more time than ideal ones. Part of what they take is not the vehicles' doing but
the margin that keeps them 3 m apart on true positions: at a 0.5 m position 1-sigma the filter
keeps sigma_k sqrt(2) sigma = 2.8 m more between a pair's estimates (6.4 m, not 3.6 m), and
routes keep sigma_k sigma = 2 m more from every keep-out zone (policy.safety.pair_radius_m,
policy/routes.py). `padded` vehicles fly as exactly as ideal ones but report a 0.5 m sigma
(policy.pointmass.VehicleModel `reported_sigma_m`), so the filter, routes and goal rule pad
for it as they do for plain GNSS: their time over ideal is the padding's own cost, the floor
under what realistic vehicles can take with it. They drift 2 cm (RTK-grade): with none at all,
antipodal circles of 16 and more are exactly symmetric, and every vehicle stops at the padded
berth at once (`padded-exact`; noise of any size breaks the tie).

policy+filter with the shipped weights, `covey eval` on the same seeds, both links. "vs ideal"
is a case's extra time over the ideal run of the same case, link and seed, a median per suite
(bench/noisy_training.py `rows`); collisions and the closest approach are on true positions.
"""

from __future__ import annotations

import argparse

from bench import common
from bench.noisy_training import fly_or_reuse, rows

LABEL = "shipped"
VARIANTS: dict[str, str] = {
    "ideal": "ideal",
    "padded": "ideal:drift_m=0.02,reported_sigma_m=0.5",
    "padded-exact": "ideal:reported_sigma_m=0.5",
    "realistic": "realistic",
}
"""Variant -> vehicle model (policy.pointmass.VehicleModel `named`). `ideal` is the reference
of every ratio and always flown."""
TARGET = 1.15
"""Issue 35: realistic vehicles at most 15 % above the ideal-vehicle time."""


def plot(table: list[dict], variants: list[str]) -> None:
    """Median extra time over ideal, by suite and link, per variant."""
    plt = common.pyplot()
    keys = sorted({(r["suite"], r["link"]) for r in table})
    shown = [v for v in variants if v != "ideal"]
    fig, ax = plt.subplots(figsize=(1.6 + 1.2 * len(keys), 3.6))
    width = 0.8 / max(len(shown), 1)
    for i, v in enumerate(shown):
        ys = []
        for k in keys:
            hit = [r for r in table if (r["suite"], r["link"]) == k and r["vehicles"] == v]
            ys.append((hit[0]["vs_own_ideal_median"] or 0.0) if hit else 0.0)
        ax.bar([j + i * width for j in range(len(keys))], ys, width, label=f"{v}: {VARIANTS[v]}")
    ax.axhline(TARGET, color="k", lw=1, ls=":", label=f"target {TARGET}")
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(keys))])
    ax.set_xticklabels([f"{s}\n{ln}" for s, ln in keys], fontsize=8)
    ax.set_ylabel("extra time / ideal vehicles' (median)")
    ax.set_ylim(0.9, None)
    ax.legend(fontsize=7)
    ax.set_title("policy+filter: the 0.5 m padding's own cost (padded) and realistic vehicles'")
    fig.tight_layout()
    common.save_figure(fig, "berth_floor")


def main(seeds: list[int], suites: tuple, variants: list[str], reuse: bool = False) -> dict:
    """Flies (or with `reuse`, reads what an earlier run left under runs/bench/berth_floor)
    every variant and seed; prints and plots the table."""
    work = common.REPO / "runs" / "bench" / "berth_floor"
    variants = ["ideal", *(v for v in variants if v != "ideal")]
    runs = {}
    for v in variants:
        for seed in seeds:
            what = f"{v} vehicles ({VARIANTS[v]}), seed {seed}"
            runs[(LABEL, v, seed)] = fly_or_reuse(
                work / f"{v}_{seed}", reuse, what, None, None, VARIANTS[v], seed, suites
            )
    table = [{k: r[k] for k in r if k != "weights"} for r in rows(runs)]
    plot(table, variants)
    print("vehicles      suite     link      runs  coll  failed  closest  vs ideal")
    for r in table:
        own = r["vs_own_ideal_median"]
        print(
            f"{r['vehicles']:13s} {r['suite']:9s} {r['link']:9s} {r['runs']:4d}  "
            f"{r['collision_cases']:4d}  {r['failed_cases']:6d}  {r['closest_true_m'] or 0:6.2f}"
            f"  {'-' if own is None else f'{own:.3f}':>8s}"
        )
    return {
        "variants": {v: VARIANTS[v] for v in variants},
        "seeds": seeds,
        "suites": list(suites),
        "target": TARGET,
        "rows": table,
    }


def _variants(spec: str) -> list[str]:
    out = [s.strip() for s in spec.split(",") if s.strip()]
    bad = [v for v in out if v not in VARIANTS]
    if bad or not out:
        raise argparse.ArgumentTypeError(
            f"variants must be among {', '.join(VARIANTS)}, got {spec!r}"
        )
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    common.add_eval_flags(
        ap,
        "321,322",
        "circle,conflict,zones",
        "read the results.json an earlier run left under runs/bench/berth_floor",
    )
    ap.add_argument(
        "--variants",
        type=_variants,
        default=["ideal", "padded", "realistic"],
        help=f"comma list of {', '.join(VARIANTS)} (ideal is always flown)",
    )
    args = ap.parse_args()
    seeds, suites = common.eval_flags(args)
    common.write_json("berth_floor", main(seeds, suites, args.variants, args.reuse))
