"""Host time of one C policy evaluation vs vehicle count (median of timed batches).

    python -m bench.firmware_host        # prints a table, writes bench/results/firmware_host.json

Builds firmware/host/covey_bench.c (hostbuild.OPT_FLAGS: -O3 -march=native, system cc)
against the shipped weights; for each neighbour count it times 15 batches of 20
covey_command calls and reports the median and the fastest batch per call. For comparison
it times the numpy runtime the same way: `GuidancePolicy.actor.action` (the same network without
the safety filter) and `GuidancePolicy.command` (world units, checks, and the filter).
The machine is shared, so the minimum is the steadier number.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from firmware import hostbuild

RESULTS = Path(__file__).resolve().parent / "results"
N_VEHICLES = (2, 5, 10, 20, 35)


def time_c(neighbours) -> dict[int, tuple[float, float]]:
    exe = hostbuild.build_bench(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    out = subprocess.run(
        [str(exe), *map(str, neighbours)], capture_output=True, text=True, check=True
    ).stdout
    return {int(t[0]): (float(t[1]), float(t[2])) for t in (ln.split() for ln in out.splitlines())}


def time_numpy(
    neighbours, repeats: int = 15, batch: int = 5, command: bool = False
) -> dict[int, tuple[float, float]]:
    """`action` (policy units, no filter) or, with `command`, `command` with the filter."""
    from policy.observation import Observation
    from policy.runtime import GuidancePolicy

    # told the whole 3 m, without the sparse rule: every neighbour is fed to the network
    pol = GuidancePolicy.load(safety_filter=command, policy_separation_m=3.0, sparse_rule=False)
    rng = np.random.default_rng(0)
    out = {}
    own, vel, goal = np.zeros(2), np.array([1.0, 0.0]), np.array([40.0, 25.0])
    # action: the old dense scene (all within 6 m, every neighbour fed); command: neighbours
    # spread over +-15 m (bench.policy_runtime's scene), as a separation-keeping swarm flies
    spread_m = 15.0 if command else 6.0
    for k in neighbours:
        nbr = rng.uniform(-spread_m, spread_m, (k, 2))
        hdg = rng.uniform(-np.pi, np.pi, k)
        nbr_vel = rng.normal(0, 0.7, (k, 2))

        obs = Observation.at_rest(own, 0.3, goal, nbr, hdg)

        def call(nbr=nbr, hdg=hdg, nbr_vel=nbr_vel, obs=obs):
            if command:
                pol.command(own, vel, 0.3, goal, nbr, nbr_vel, hdg)
            else:
                pol.actor.action(obs)

        call()
        per_call = []
        for _ in range(repeats):
            t0 = time.perf_counter_ns()
            for _ in range(batch):
                call()
            per_call.append((time.perf_counter_ns() - t0) / batch)
        out[k] = (float(np.median(per_call)), float(np.min(per_call)))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS / "firmware_host.json")
    args = parser.parse_args(argv)
    ks = [n - 1 for n in N_VEHICLES]
    c_ns = time_c(ks)
    np_ns = time_numpy(ks)
    cmd_ns = time_numpy(ks, command=True)
    rows = [
        {
            "vehicles": k + 1,
            "neighbours": k,
            "c_median_us": c_ns[k][0] / 1e3,
            "c_min_us": c_ns[k][1] / 1e3,
            "numpy_median_us": np_ns[k][0] / 1e3,
            "numpy_min_us": np_ns[k][1] / 1e3,
            "numpy_command_filter_median_us": cmd_ns[k][0] / 1e3,
            "numpy_command_filter_min_us": cmd_ns[k][1] / 1e3,
        }
        for k in ks
    ]
    print(" N   C median us   C min us   numpy median us   numpy min us   command+filter med/min")
    for r in rows:
        print(
            f"{r['vehicles']:2d} {r['c_median_us']:12.1f} {r['c_min_us']:10.1f} "
            f"{r['numpy_median_us']:16.1f} {r['numpy_min_us']:14.1f} "
            f"{r['numpy_command_filter_median_us']:12.1f} {r['numpy_command_filter_min_us']:8.1f}"
        )
    result = {
        "machine": platform.processor() or platform.machine(),
        "compiler": hostbuild.compiler(),
        "flags": " ".join(hostbuild.OPT_FLAGS),
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
