"""Intruders: a vehicle that does not cooperate flies straight through the fleet (covey eval's
`intruder` suite: head-on, crossing, through a block of 10, through forced conflicts and a
circle swap, at 1x, 1.5x and 2x the fleet's speed), on the perfect and the 3 Hz lossy link;
and manned aircraft (the `manned` suite: 20, 40 and 60 m/s, heard 30 s before they pass),
whose 30 m berth the fleet keeps (`manned_entries`: covey vehicles that came closer).

Compared: the controllers (numpy, the C core, ORCA) told which vehicle does not cooperate (the
filter takes the whole correction for it, steps aside of it on its own line and keeps its
line hard) against the same controllers taking it for a covey vehicle (the reciprocal half,
before issue 35); ideal and realistic vehicles; the non-cooperative berth at the separation
and at 4 m. Collisions are judged on true positions, below 3 m.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from firmware.ceval import CONTROLLERS as C_CONTROLLERS
from policy.eval import EvalConfig
from policy.eval import main as eval_main

RESULTS = Path(__file__).resolve().parent / "results"
CONTROLLERS = ("policy+filter", "c+filter", "orca")
VARIANTS = {
    "marked": {},
    "unmarked": {"mark_non_cooperative": False},
    "marked-berth-4m": {"non_cooperative_separation_m": 4.0},
    "marked-realistic": {"vehicles": "realistic"},
    "manned": {"suites": ("manned",)},
    "manned-realistic": {"suites": ("manned",), "vehicles": "realistic"},
}
"""name -> EvalConfig overrides (suites: the intruder suite unless named)."""


def _rows(result: dict) -> list[dict]:
    keep = (
        "case",
        "link",
        "controller",
        "collisions",
        "min_sep",
        "intruder_min_sep",
        "manned_entries",
        "manned_min_sep",
        "success",
        "extra_time",
    )
    return [{k: r.get(k) for k in keep} for r in result["runs"]]


def _median(values) -> float | None:
    v = [x for x in values if x is not None]
    return statistics.median(v) if v else None


def main(quick: bool = False) -> dict:
    out: dict = {"controllers": list(CONTROLLERS), "variants": {}}
    for name, overrides in VARIANTS.items():
        if quick and name not in ("marked", "manned"):
            continue
        cfg = EvalConfig(
            out=f"/tmp/covey-bench-intruder/{name}",
            controllers=CONTROLLERS,
            figures=False,
            progress=False,
            quick=quick,
            **{"suites": ("intruder",), **overrides},
        )
        t0 = time.perf_counter()
        result = eval_main(cfg, C_CONTROLLERS)
        runs = _rows(result)
        summary = {}
        for link in cfg.links:
            for ctrl in CONTROLLERS:
                mine = [r for r in runs if r["link"] == link and r["controller"] == ctrl]
                by_ratio = {}
                for ratio in dict.fromkeys(r["case"].split("-")[1] for r in mine):  # 1x, 20m_s
                    rs = [r for r in mine if r["case"].split("-")[1] == ratio]
                    by_ratio[ratio] = {
                        "cases": len(rs),
                        "collision_cases": sum(1 for r in rs if r["collisions"]),
                        "closest_to_intruder_m": min(
                            (r["intruder_min_sep"] for r in rs if r["intruder_min_sep"]),
                            default=None,
                        ),
                        "closest_m": min((r["min_sep"] for r in rs if r["min_sep"]), default=None),
                        "manned_entries": sum(r.get("manned_entries") or 0 for r in rs),
                        "median_extra_time": _median(r["extra_time"] for r in rs),
                    }
                summary[f"{link}/{ctrl}"] = by_ratio
        out["variants"][name] = {
            "config": overrides,
            "seconds": round(time.perf_counter() - t0, 1),
            "summary": summary,
            "collided": [r for r in runs if r["collisions"]],
        }
    return out


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    res = main(a.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "intruder.json").write_text(json.dumps(res, indent=1))
    for variant, v in res["variants"].items():
        for key, by_ratio in v["summary"].items():
            cells = "  ".join(
                f"{r}: {s['collision_cases']}/{s['cases']} ({s['closest_to_intruder_m'] or 0:.2f} m"
                + (f", {s['manned_entries']} in berth)" if variant.startswith("manned") else ")")
                for r, s in by_ratio.items()
            )
            print(f"{variant:18s} {key:24s} {cells}")
