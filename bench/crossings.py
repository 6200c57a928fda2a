"""Two vehicles crossing: extra time of the policy with its filter, with and without the
sparse-traffic rule (policy/sparse.py), and of ORCA, over crossing angles and timing offsets.

    python -m bench.crossings [--quick]   # table; bench/results/crossings.{json,png}

Each case: vehicle A flies 60 m along x through the origin; B crosses it at `angle` degrees,
starting `offset` m further out, so that it reaches the crossing that much later (0 = both at
once, dead-on; 180 = head-on on one line). Policy units (3 m separation, 1 m/s), perfect link,
dt 0.1 s, as `covey eval`. Extra time = mean over both of flight time / straight-line time.
These encounters are not among `covey eval`'s cases: they isolate what the rule is for.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from bench import common

ANGLES_DEG = (30, 60, 90, 120, 150, 180)
OFFSETS_M = (0.0, 0.5, 1.0, 2.0, 3.0)
CONTROLLERS = ("rule", "policy", "orca")
"""rule: policy+filter as flown (sparse rule on); policy: the same without the rule; orca: the
straight line through the same filter."""


def crossing(angle_deg: float, offset_m: float, leg_m: float = 30.0):
    """Starts and goals (2, 2) of one crossing."""
    t = math.radians(angle_deg)
    u = np.array([math.cos(t), math.sin(t)])
    starts = np.array([[-leg_m, 0.0], -(leg_m + offset_m) * u])
    goals = np.array([[leg_m, 0.0], leg_m * u])
    return starts, goals


def fly_all(angles=ANGLES_DEG, offsets=OFFSETS_M) -> list[dict]:
    from policy import evalsim
    from policy.eval import EvalConfig, controllers

    with_rule = controllers(EvalConfig(figures=False, progress=False))
    without = controllers(EvalConfig(figures=False, progress=False, sparse_rule=False))
    ctrls = {
        "rule": with_rule["policy+filter"],
        "policy": without["policy+filter"],
        "orca": without["orca"],
    }
    rows = []
    for angle in angles:
        for offset in offsets:
            starts, goals = crossing(angle, offset)
            row = {"angle_deg": angle, "offset_m": offset}
            for name, ctrl in ctrls.items():
                if hasattr(ctrl, "reset"):
                    ctrl.reset()
                r = evalsim.run(
                    starts,
                    goals,
                    ctrl,
                    evalsim.PERFECT,
                    evalsim.EvalSimConfig(),
                    np.random.default_rng(0),
                )
                row[f"{name}_extra_time"] = float(r["extra_time"])
                row[f"{name}_min_sep_m"] = float(r["min_sep"])
                row[f"{name}_collisions"] = int(r["collisions"])
            rows.append(row)
    return rows


def summary(rows: list[dict]) -> dict:
    out = {}
    for name in CONTROLLERS:
        e = np.array([r[f"{name}_extra_time"] for r in rows])
        out[name] = {
            "mean_extra_time": float(e.mean()),
            "median_extra_time": float(np.median(e)),
            "max_extra_time": float(e.max()),
            "min_sep_m": float(min(r[f"{name}_min_sep_m"] for r in rows)),
            "collisions": int(sum(r[f"{name}_collisions"] for r in rows)),
        }
    best_other = np.array([min(r["policy_extra_time"], r["orca_extra_time"]) for r in rows])
    rule = np.array([r["rule_extra_time"] for r in rows])
    out["rule_within_0p5pct_of_the_better_other"] = int((rule <= best_other + 0.005).sum())
    out["cases"] = len(rows)
    return out


def plot(rows: list[dict]) -> None:
    plt = common.pyplot()
    angles = sorted({r["angle_deg"] for r in rows})
    offsets = sorted({r["offset_m"] for r in rows})
    fig, axes = plt.subplots(1, len(offsets), figsize=(3.0 * len(offsets), 3.4), sharey=True)
    axes = np.atleast_1d(axes)
    styles = {"rule": ("C0", "o-"), "policy": ("C1", "s--"), "orca": ("C2", "^:")}
    for ax, off in zip(axes, offsets, strict=True):
        for name, (color, style) in styles.items():
            ys = [
                next(r for r in rows if r["angle_deg"] == a and r["offset_m"] == off)[
                    f"{name}_extra_time"
                ]
                for a in angles
            ]
            ax.plot(angles, ys, style, color=color, label=name)
        ax.set_title(f"B {off:g} m later")
        ax.set_xlabel("crossing angle (deg)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("extra time (flight / straight line)")
    axes[0].legend()
    fig.suptitle("Two vehicles crossing: policy+filter with the sparse rule, without it, ORCA")
    fig.tight_layout()
    common.save_figure(fig, "crossings")


def main(quick: bool = False) -> dict:
    angles, offsets = ((60, 180), (0.0, 1.0)) if quick else (ANGLES_DEG, OFFSETS_M)
    common.say(f"{len(angles) * len(offsets)} crossings x {len(CONTROLLERS)} controllers")
    rows = fly_all(angles, offsets)
    result = {"rows": rows, "summary": summary(rows)}
    plot(rows)
    s = result["summary"]
    print("controller  mean   median  max    closest  collisions")
    for name in CONTROLLERS:
        m = s[name]
        print(
            f"{name:10s} {m['mean_extra_time']:.4f} {m['median_extra_time']:.4f} "
            f"{m['max_extra_time']:.4f} {m['min_sep_m']:.2f} m   {m['collisions']}"
        )
    print(
        f"rule within 0.5 % of the better of policy and ORCA in "
        f"{s['rule_within_0p5pct_of_the_better_other']} of {s['cases']} crossings"
    )
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 crossings instead of 30")
    args = ap.parse_args()
    common.write_json("crossings", main(args.quick))
