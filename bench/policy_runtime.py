"""Runtime timings: `python -m bench.policy_runtime [--weights W] [--repeats N]`.

Median wall time of GuidancePolicy.command with 19 neighbours and of
command_batch for 1000 vehicles with the nearest 10 neighbours, with and
without the safety filter. Run with OMP_WAIT_POLICY=PASSIVE OPENBLAS_NUM_THREADS=1.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from policy.runtime import GuidancePolicy


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3)


def main(weights=None, repeats: int = 200, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    k = 19
    pos, vel = np.zeros(2), np.array([1.0, 0.0])
    nbr_pos = rng.uniform(-15, 15, (k, 2))
    nbr_vel, nbr_h = rng.normal(0, 0.7, (k, 2)), rng.uniform(-np.pi, np.pi, k)
    n = 1000
    side = 20.0 * np.sqrt(n)
    p_n, g_n = rng.uniform(0, side, (n, 2)), rng.uniform(0, side, (n, 2))
    v_n, h_n = rng.normal(0, 0.7, (n, 2)), rng.uniform(-np.pi, np.pi, n)
    for filt in (False, True):
        pol = GuidancePolicy.load(weights, safety_filter=filt)
        out[f"command@19 filter={filt}"] = median_ms(
            lambda pol=pol: pol.command(pos, vel, 0.3, [40.0, 10.0], nbr_pos, nbr_vel, nbr_h),
            repeats,
        )
        pol = GuidancePolicy.load(weights, safety_filter=filt, max_neighbours=10)
        out[f"command_batch@1000 nearest-10 filter={filt}"] = median_ms(
            lambda pol=pol: pol.command_batch(p_n, v_n, h_n, g_n), max(repeats // 10, 5)
        )
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--repeats", type=int, default=200)
    a = ap.parse_args()
    for name, ms in main(a.weights, a.repeats).items():
        print(f"{name:45s} {ms:8.3f} ms (median)")
