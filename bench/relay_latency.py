"""What the cell relay's wait costs in safety: `covey eval` on the degraded link with its 100 ms
latency, and with 200 ms, the worst a state can wait in a router's cell relay on top (a 0.1 s
period; comms/relay.py). Realistic vehicles, policy + filter (numpy), fresh seeds.

    python -m bench.relay_latency [--quick]   # bench/results/relay_latency.json

The relay holds a state until its next period, half of it on average, so 200 ms is the worst
case of every state, not the typical one. Collisions and closest approach are on true positions.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace

from bench import common

LATENCIES_S = (0.1, 0.2)
"""The degraded link's own latency, and it plus a whole relay period."""
SEEDS = (53, 59, 61, 67)
SUITES = ("circle", "conflict", "large", "intruder")


def main(quick: bool = False) -> dict:
    import policy.eval as ev
    from policy.evalsim import DEGRADED

    seeds, suites = ((53,), ("conflict",)) if quick else (SEEDS, SUITES)
    rows = []
    try:
        for latency_s in LATENCIES_S:
            ev.DEGRADED = replace(DEGRADED, latency_s=latency_s)
            for seed in seeds:
                with tempfile.TemporaryDirectory() as out:
                    res = ev.main(
                        ev.EvalConfig(
                            out=out,
                            seed=seed,
                            links=("degraded",),
                            suites=suites,
                            vehicles="realistic",
                            figures=False,
                            progress=False,
                            controllers=("policy+filter",),
                        )
                    )
                runs = res["runs"]
                row = {
                    "latency_s": latency_s,
                    "seed": seed,
                    "runs": len(runs),
                    "collision_cases": sum(bool(r["collisions"]) for r in runs),
                    "closest_true_m": min(r["min_sep"] for r in runs),
                    "success": sum(r["success"] for r in runs) / len(runs),
                    "extra_time_median": common.pct([r["extra_time"] for r in runs], 50),
                }
                rows.append(row)
                common.say(
                    f"latency {latency_s:.1f} s, seed {seed}: {row['runs']} runs, "
                    f"{row['collision_cases']} collision cases, closest {row['closest_true_m']:.2f}"
                    f" m, success {100 * row['success']:.0f} %, extra time median "
                    f"{row['extra_time_median']:.2f}"
                )
    finally:
        ev.DEGRADED = DEGRADED
    result = {"quick": quick, "suites": list(suites), "rows": rows}
    for latency_s in LATENCIES_S:
        mine = [r for r in rows if r["latency_s"] == latency_s]
        result[f"latency_{latency_s:g}_s"] = {
            "runs": sum(r["runs"] for r in mine),
            "collision_cases": sum(r["collision_cases"] for r in mine),
            "closest_true_m": min(r["closest_true_m"] for r in mine),
        }
    common.write_json("relay_latency", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, the conflict suite")
    main(ap.parse_args().quick)
