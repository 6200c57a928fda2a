"""How a caller of the public runtime flies the policy: hold `preferred` (as the agents do),
hold `command`, or call `command` every tick; and ORCA, on forced conflicts, small circles and
random swarms.

    python -m bench.call_patterns [--quick] [--links perfect,degraded]
                                              # tables; bench/results/call_patterns.{json,png}

Each pattern goes only through `GuidancePolicy.load()` with its defaults (the agents'
configuration) and its public methods, one vehicle at a time, as an outside harness would:
- `hold preferred`: `preferred` every `decision_period_s`, `filter` of the held velocity every
  tick (agent.guidance, covey_guidance_step);
- `hold command`: the same with `command` held (already filtered when it decided);
- `command every tick`: `command` at every step;
- `orca`: `filter` of the straight line at the goal.

Flown in policy.evalsim (policy units: 3 m separation, 1 m/s, dt 0.1 s). The circles start at
a 10 m radius (`covey eval`'s start at 20 m), so the vehicles see each other from the start.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench import common

PATTERNS = ("hold preferred", "hold command", "command every tick", "orca")
SUITES = ("conflict", "circle", "large")
LINKS = ("perfect", "degraded")
METRICS = ("extra_time", "min_sep", "collisions", "success", "mean_acc")
"""Per case and pattern, from policy.evalsim.run."""


class PublicCaller:
    """An evalsim controller that flies one calling pattern of the public per-vehicle API."""

    def __init__(self, pol, pattern: str) -> None:
        if pattern not in PATTERNS:
            raise ValueError(f"pattern must be one of {PATTERNS}, got {pattern!r}")
        self.pol, self.pattern = pol, pattern
        self.reset()

    def reset(self) -> None:
        self.held: dict[int, np.ndarray] = {}
        self.next_s: dict[int, float] = {}

    def __call__(self, ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, valid):
        from policy.sparse import straight_velocity

        pol, out = self.pol, np.zeros_like(pos)
        for r, vid in enumerate(ids.tolist()):
            m = valid[r]
            n_pos, n_vel, n_head = nbr_pos[r][m], nbr_vel[r][m], nbr_heading[r][m]
            args = (pos[r], vel[r], float(heading[r]), goal[r], n_pos, n_vel, n_head)
            if self.pattern == "command every tick":
                out[r] = pol.command(*args)
                continue
            if self.pattern == "orca":
                want = straight_velocity(
                    pos[r], goal[r], pol.cruise_speed_m_s, pol.decision_period_s
                )
            else:
                if t_s >= self.next_s.get(vid, -np.inf) - 1e-9:
                    decide = pol.preferred if self.pattern == "hold preferred" else pol.command
                    self.held[vid] = decide(*args)
                    self.next_s[vid] = t_s + pol.decision_period_s
                want = self.held[vid]
            out[r] = pol.filter(pos[r], vel[r], want, n_pos, n_vel) if len(n_pos) else want
        return out


def cases(quick: bool, rng: np.random.Generator) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    from policy import scenarios

    conflict_ns = (3, 6) if quick else (2, 3, 4, 5, 6, 8, 10)
    per_n = 1 if quick else 3
    circle_ns = (4, 8) if quick else (2, 4, 8, 12, 16, 24, 32, 50)
    large_ns = () if quick else (35, 35, 35, 100)
    out = [
        ("conflict", f"conflict-{n}-{k}", *scenarios.random_conflict(rng, n))
        for n in conflict_ns
        for k in range(per_n)
    ]
    out += [
        ("circle", f"circle-{n}", *scenarios.antipodal_circle(n, min_radius_m=10.0))
        for n in circle_ns
    ]
    out += [
        ("large", f"large-{n}-{k}", *scenarios.random_large(rng, n)) for k, n in enumerate(large_ns)
    ]
    return out


def fly_all(quick: bool, link_name: str, seed: int = 0) -> list[dict]:
    from policy import evalsim
    from policy.runtime import GuidancePolicy

    link = {"perfect": evalsim.PERFECT, "degraded": evalsim.DEGRADED}[link_name]
    pol = GuidancePolicy.load()  # the defaults: as the agents fly
    rows = []
    for i, (suite, name, starts, goals) in enumerate(cases(quick, np.random.default_rng(seed))):
        runs = {
            p: evalsim.run(
                starts,
                goals,
                PublicCaller(pol, p),
                link,
                evalsim.EvalSimConfig(),
                np.random.default_rng([seed, i]),
            )
            for p in PATTERNS
        }
        # flat, the extra times first (bench/report.py shows the first columns)
        row = {"suite": suite, "case": name, "n": int(len(starts))}
        for metric in METRICS:
            row.update({_key(p, metric): runs[p][metric] for p in PATTERNS})
        rows.append(row)
        common.say(
            f"{name}: " + ", ".join(f"{p} {_fmt(row[_key(p, 'extra_time')])}" for p in PATTERNS)
        )
    return rows


def _key(pattern: str, metric: str) -> str:
    return f"{pattern.replace(' ', '_')}_{metric}"


def _fmt(extra_time) -> str:
    return f"{extra_time:.3f}" if extra_time is not None else "-"


def summary(rows: list[dict]) -> dict:
    """Per suite and pattern: cases, all arrived, collisions, closest approach, mean extra time
    over the cases where every vehicle arrived, mean |commanded acceleration|."""
    out = {}
    for suite in SUITES:
        mine = [r for r in rows if r["suite"] == suite]
        if not mine:
            continue
        out[suite] = {}
        for p in PATTERNS:
            ok = [r[_key(p, "extra_time")] for r in mine if r[_key(p, "success")]]
            seps = [r[_key(p, "min_sep")] for r in mine if r[_key(p, "min_sep")] is not None]
            out[suite][p] = {
                "cases": len(mine),
                "succeeded": len(ok),
                "collisions": int(sum(r[_key(p, "collisions")] for r in mine)),
                "min_sep_m": float(min(seps)) if seps else None,
                "mean_extra_time": float(np.mean(ok)) if ok else None,
                "mean_acc_m_s2": float(np.mean([r[_key(p, "mean_acc")] for r in mine])),
            }
    return out


def plot(by_link: dict[str, dict]) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, len(by_link), figsize=(7.0 * len(by_link), 3.8), squeeze=False)
    for ax, (link_name, s) in zip(axes[0], by_link.items(), strict=True):
        _bars(ax, s, link_name)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    common.save_figure(fig, "call_patterns")


def _bars(ax, s: dict, link_name: str) -> None:
    suites = list(s)
    width = 0.8 / len(PATTERNS)
    for j, p in enumerate(PATTERNS):
        # a suite where some case got stuck has no mean: no bar, a label instead
        ys = [
            (s[x][p]["mean_extra_time"] or np.nan)
            if s[x][p]["succeeded"] == s[x][p]["cases"]
            else np.nan
            for x in suites
        ]
        xs = np.arange(len(suites)) + (j - (len(PATTERNS) - 1) / 2) * width
        ax.bar(xs, np.asarray(ys) - 1.0, width, bottom=1.0, label=p)
        for x, y, suite in zip(xs, ys, suites, strict=True):
            m = s[suite][p]
            if m["succeeded"] < m["cases"]:
                stuck = m["cases"] - m["succeeded"]
                ax.text(x, 1.0, f"{stuck} of {m['cases']} stuck", rotation=90, fontsize=7)
            elif np.isfinite(y):
                ax.text(x, y, f"{y:.3f}", ha="center", va="bottom", fontsize=6)
    ax.set_xticks(np.arange(len(suites)), suites)
    ax.set_ylabel("mean extra time (flight / straight line)")
    ax.set_title(f"Calling the runtime: {link_name} link")
    ax.grid(alpha=0.3, axis="y")


def main(quick: bool = False, links: tuple[str, ...] = LINKS) -> dict:
    if not links or not set(links) <= set(LINKS):
        raise ValueError(f"links must be some of {LINKS}, got {links!r}")
    out = {}
    for link_name in links:
        rows = fly_all(quick, link_name)
        out[link_name] = {"rows": rows, "summary": summary(rows)}
    plot({k: v["summary"] for k, v in out.items()})
    for link_name, res in out.items():
        print(f"link {link_name}")
        print("suite     pattern              ok      coll  closest  extra   |acc|")
        for suite, per in res["summary"].items():
            for p, m in per.items():
                extra = f"{m['mean_extra_time']:.4f}" if m["mean_extra_time"] else "  -   "
                print(
                    f"{suite:9s} {p:20s} {m['succeeded']:2d}/{m['cases']:<2d}  "
                    f"{m['collisions']:4d}  {m['min_sep_m']:.2f} m  {extra}  "
                    f"{m['mean_acc_m_s2']:.3f}"
                )
    table = [
        {"link": link_name, "suite": suite, "pattern": p, **m}
        for link_name, res in out.items()
        for suite, per in res["summary"].items()
        for p, m in per.items()
    ]
    return {"table": table, "links": out}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 cases instead of 33, perfect link")
    ap.add_argument(
        "--links",
        type=lambda v: tuple(x for x in v.split(",") if x),
        default=None,
        help="comma-separated, of perfect,degraded (default both; --quick: perfect)",
    )
    args = ap.parse_args()
    links = args.links or (("perfect",) if args.quick else LINKS)
    common.write_json("call_patterns", main(args.quick, links))
