"""Dense circles under the filter's parting rule: the old rule (part within one dt) against the
shipped one (padding-only pairs part at up to recover_speed_share x max speed), per regime.

    python -m bench.parting_circles [--quick] [--seeds 21-23] [--regimes drift-0.75,gusty]
                                    [--rules old,shipped]
    # table; bench/results/parting_circles.json, docs/bench_parting_circles.png

What docs/sky.md "Parting pairs" measured: antipodal circles of 16, 32 and 50 (every vehicle
through the centre), policy + filter as `covey eval` flies it (bench/crowd_sigma.py `_fly`),
sigma_k 4, the perfect and the 3 Hz lossy link, each seed drawing its own noise and losses,
every rule flying the same seeds. A regime is a vehicle model (policy.pointmass.VehicleModel
`named`); a rule is the filter's `SafetyConfig.recover_speed_share` (0: RVO2's rule, before).
Collisions (a pair under 3 m) and the closest approach are on true positions; "late" counts
vehicles that did not arrive in time; extra time is the mean over runs of each run's mean
arrival time over the straight-line time.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass

from bench import common
from bench.crowd_sigma import LINKS, _fly
from policy.safety import RECOVER_SPEED_SHARE

REGIMES: dict[str, str] = {
    "drift-0.75": "realistic:drift_m=0.75",
    "drift-1.0": "realistic:drift_m=1.0",
    "gusty": "realistic:gust_m_s=0.5,lag_s=0.5",
}
"""Regime -> vehicle model: realistic vehicles (0.3 s lag, 2.5 m/s^2, 0.2 m/s gusts, 0.5 m GNSS)
with GNSS drifting 0.75 or 1 m, or with 0.5 m/s gusts and a 0.5 s velocity loop (plain GNSS)."""
RULES: dict[str, float] = {"old": 0.0, "shipped": RECOVER_SPEED_SHARE}
"""Rule -> SafetyConfig.recover_speed_share: 0 parts within one dt (RVO2, before); shipped is
the default (policy.safety.RECOVER_SPEED_SHARE, 2: each vehicle of a pair at its full speed)."""
CIRCLES = (16, 32, 50)
COLLIDE_M = 3.0
"""The separation: a run with a true pair distance under it has a collision."""


@dataclass(frozen=True)
class PartingConfig:
    """One bench run: every regime x rule x seed x circle x link."""

    regimes: tuple[str, ...] = tuple(REGIMES)
    """Names in REGIMES."""
    rules: tuple[str, ...] = tuple(RULES)
    """Names in RULES."""
    seeds: tuple[int, ...] = (21, 22, 23)
    """Scenario and noise seeds; every rule flies the same ones."""
    circles: tuple[int, ...] = CIRCLES
    """Antipodal circle sizes (vehicles)."""
    links: tuple[str, ...] = LINKS
    """perfect and/or degraded (3 Hz, lossy)."""
    sigma_k: float = 4.0
    """The filter's confidence factor (policy.safety.SIGMA_K)."""

    def __post_init__(self) -> None:
        for what, given, known in (
            ("regime", self.regimes, REGIMES),
            ("rule", self.rules, RULES),
            ("link", self.links, LINKS),
        ):
            bad = [x for x in given if x not in known]
            if bad or not given:
                raise ValueError(
                    f"{what}s {', '.join(bad) or '(none)'}: choose among {', '.join(known)}"
                )
        if not self.seeds or not self.circles:
            raise ValueError("at least one seed and one circle are needed")
        if any(n < 2 for n in self.circles):
            raise ValueError(f"circles need 2 vehicles or more, got {self.circles}")


def quick_config() -> PartingConfig:
    """One small circle, one seed, every regime and rule: a smoke run."""
    return PartingConfig(seeds=(21,), circles=(16,))


def summarise(rows: list[dict]) -> list[dict]:
    """One record per (regime, rule), in the order first seen: runs, runs with a collision,
    closest and median closest true approach, vehicles late, mean extra time."""
    keys = list(dict.fromkeys((r["regime"], r["rule"]) for r in rows))
    out = []
    for regime, rule in keys:
        mine = [r for r in rows if r["regime"] == regime and r["rule"] == rule]
        seps = [r["min_sep"] for r in mine if r["min_sep"] is not None]
        extra = [r["extra_time"] for r in mine if r["extra_time"] is not None]
        out.append(
            {
                "regime": regime,
                "rule": rule,
                "recover_speed_share": mine[0]["recover_speed_share"],
                "runs": len(mine),
                "collision_runs": sum(r["collisions"] > 0 for r in mine),
                "closest_true_m": min(seps) if seps else None,
                "median_closest_true_m": statistics.median(seps) if seps else None,
                "vehicles_late": sum(r["timeouts"] for r in mine),
                "mean_extra_time": statistics.fmean(extra) if extra else None,
            }
        )
    return out


def _num(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def table(summary: list[dict]) -> str:
    """The summary as a fixed-width text table, one line per (regime, rule)."""
    head = (
        f"{'regime':12s} {'rule':8s} {'share':>5s}  {'collision runs':>14s}  {'closest m':>9s}  "
        f"{'median m':>8s}  {'late':>4s}  {'extra time':>10s}"
    )
    lines = [head]
    for s in summary:
        coll = f"{s['collision_runs']} of {s['runs']}"
        lines.append(
            f"{s['regime']:12s} {s['rule']:8s} {s['recover_speed_share']:5g}  {coll:>14s}  "
            f"{_num(s['closest_true_m'], '.2f'):>9s}  {_num(s['median_closest_true_m'], '.2f'):>8s}"
            f"  {s['vehicles_late']:4d}  {_num(s['mean_extra_time'], '.3f'):>10s}"
        )
    return "\n".join(lines)


def plot(summary: list[dict]) -> None:
    """Collision runs, closest (bar) and median closest (mark) true approach, mean extra time:
    one group per regime, one bar per rule."""
    plt = common.pyplot()
    regimes = list(dict.fromkeys(s["regime"] for s in summary))
    rules = list(dict.fromkeys(s["rule"] for s in summary))
    cell = {(s["regime"], s["rule"]): s for s in summary}
    fig, axes = plt.subplots(1, 3, figsize=(13.0, 3.8))
    width = 0.8 / len(rules)
    for j, rule in enumerate(rules):
        xs = [i + (j - (len(rules) - 1) / 2) * width for i in range(len(regimes))]
        got = [cell.get((g, rule)) for g in regimes]
        share = next(s["recover_speed_share"] for s in got if s)
        label = f"{rule} (share {share:g})"
        axes[0].bar(xs, [s["collision_runs"] if s else 0 for s in got], width, label=label)
        axes[1].bar(xs, [(s["closest_true_m"] or 0) if s else 0 for s in got], width, label=label)
        axes[1].plot(xs, [s["median_closest_true_m"] if s else None for s in got], "k_", ms=12)
        axes[2].bar(xs, [(s["mean_extra_time"] or 0) if s else 0 for s in got], width, label=label)
    runs = summary[0]["runs"]
    axes[0].set_ylim(0, max(1, *(s["collision_runs"] for s in summary)) + 0.5)
    axes[0].yaxis.get_major_locator().set_params(integer=True)
    axes[0].set_ylabel(f"runs with a collision (of {runs})")
    axes[1].set_ylabel("closest true approach, m (mark: median)")
    axes[1].axhline(COLLIDE_M, color="grey", lw=0.8)
    axes[2].set_ylabel("mean extra time (x straight line)")
    axes[2].set_ylim(bottom=1.0)
    for ax in axes:
        ax.set_xticks(range(len(regimes)), regimes)
    axes[0].legend(fontsize=8)
    fig.suptitle("dense antipodal circles: parting within dt (old) against the shipped cap")
    fig.tight_layout()
    common.save_figure(fig, "parting_circles")


def main(cfg: PartingConfig) -> dict:
    t0 = time.monotonic()
    tasks = [(g, rule, s) for g in cfg.regimes for rule in cfg.rules for s in cfg.seeds]
    rows: list[dict] = []
    for i, (regime, rule, seed) in enumerate(tasks, 1):
        share = RULES[rule]
        got = _fly(REGIMES[regime], cfg.sigma_k, seed, cfg.circles, cfg.links, share)
        rows += [{"regime": regime, "rule": rule, "recover_speed_share": share, **r} for r in got]
        hit = sum(r["collisions"] > 0 for r in got)
        common.say(
            f"[{i}/{len(tasks)}] {regime}, {rule}, seed {seed}: {hit} of {len(got)} runs with a "
            f"collision, closest {min(r['min_sep'] for r in got):.2f} m "
            f"({time.monotonic() - t0:.0f} s)"
        )
    summary = summarise(rows)
    print(table(summary))
    plot(summary)
    result = {
        "regimes": {g: REGIMES[g] for g in cfg.regimes},
        "rules": {r: RULES[r] for r in cfg.rules},
        "seeds": list(cfg.seeds),
        "circles": list(cfg.circles),
        "links": list(cfg.links),
        "sigma_k": cfg.sigma_k,
        "summary": summary,
        "runs": rows,
        "wall_s": round(time.monotonic() - t0, 1),
    }
    common.write_json("parting_circles", result)
    return result


def seed_list(text: str) -> tuple[int, ...]:
    """argparse `type` of --seeds: '21,22,23' or '21-27' (ranges inclusive, may be mixed)."""
    out: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        lo, dash, hi = part.partition("-")
        try:
            a = int(lo)
            b = int(hi) if dash else a
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: {part!r} is not a seed or a range of seeds (21,22 or 21-27)"
            ) from None
        if a < 0 or b < a:
            raise argparse.ArgumentTypeError(f"{text!r}: {part!r} is negative or runs backwards")
        out.extend(range(a, b + 1))
    return tuple(dict.fromkeys(out))


if __name__ == "__main__":
    from cli.options import comma_list

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one circle of 16, seed 21")
    ap.add_argument("--seeds", type=seed_list, default=None, help="seeds (default 21-23)")
    ap.add_argument(
        "--regimes",
        type=comma_list,
        default=tuple(REGIMES),
        help=f"comma list of {', '.join(REGIMES)} (default all)",
    )
    ap.add_argument(
        "--rules",
        type=comma_list,
        default=tuple(RULES),
        help=f"comma list of {', '.join(RULES)} (default both)",
    )
    a = ap.parse_args()
    base = quick_config() if a.quick else PartingConfig()
    try:
        cfg = PartingConfig(
            regimes=a.regimes,
            rules=a.rules,
            seeds=a.seeds or base.seeds,
            circles=base.circles,
        )
    except ValueError as e:
        ap.error(str(e))
    main(cfg)
