"""Runtime timings: `python -m bench.policy_runtime [--weights W] [--repeats N] [--quick]`.

Median wall time of GuidancePolicy.command with 19 neighbours and of
command_batch for 1000 vehicles with the nearest 10 neighbours, with and
without the safety filter; and command as the agents decide, with the sparse rule. Run with OMP_WAIT_POLICY=PASSIVE OPENBLAS_NUM_THREADS=1.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from policy.observation import Swarm
from policy.runtime import GuidancePolicy
from policy.sparse import SparseConfig


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
    swarm = Swarm.checked(p_n, v_n, h_n, g_n)
    # told the whole 3 m (not flight's 1.25 m, whose 8.3 m sense range would drop most of these
    # neighbours): every one is fed to the network, the dearest case; the rule is timed below
    wide = dict(policy_separation_m=3.0, sparse_rule=False)
    for filt in (False, True):
        pol = GuidancePolicy.load(weights, safety_filter=filt, **wide)
        out[f"command@19 filter={filt}"] = median_ms(
            lambda pol=pol: pol.command(pos, vel, 0.3, [40.0, 10.0], nbr_pos, nbr_vel, nbr_h),
            repeats,
        )
        pol = GuidancePolicy.load(weights, safety_filter=filt, max_neighbours=10, **wide)
        out[f"command_batch@1000 nearest-10 filter={filt}"] = median_ms(
            lambda pol=pol: pol.command_batch(swarm), max(repeats // 10, 5)
        )
    # the agents' decision: with the sparse rule (policy/sparse.py) too, timed in alternating
    # rounds against the same call without it (ratios from one run). Two scenes: the one above
    # (the rule keeps the policy) and every neighbour co-moving 7-18 m away (it flies straight:
    # its dearer case, one more filter call)
    ang, rad = rng.uniform(0, 2 * np.pi, k), rng.uniform(7, 18, k)
    apart = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=1)
    scenes = {
        "": ([40.0, 10.0], 0.3, nbr_pos, nbr_vel, nbr_h),
        ", straight": ([40.0, 0.0], 0.0, apart, np.tile([1.0, 0.0], (k, 1)), np.zeros(k)),
    }
    pols = {
        False: GuidancePolicy.load(weights, safety_filter=True, **wide),
        True: GuidancePolicy.load(
            weights, safety_filter=True, policy_separation_m=3.0, sparse_rule=SparseConfig()
        ),
    }
    for tag, (goal, hdg, n_pos, n_vel, n_h) in scenes.items():
        args = (pos, vel, hdg, goal, n_pos, n_vel, n_h)
        rounds = {False: [], True: []}
        for _ in range(9):
            for rule, pol in pols.items():
                rounds[rule].append(
                    median_ms(lambda pol=pol, args=args: pol.command(*args), max(repeats // 9, 5))
                )
        base, ruled = float(np.median(rounds[False])), float(np.median(rounds[True]))
        out[f"command@19 filter=True{tag}"] = base
        out[f"command@19 filter=True sparse_rule=True{tag}"] = ruled
        out[f"ratio sparse_rule{tag}"] = ruled / base
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--quick", action="store_true", help="smoke-sized: 20 repeats")
    a = ap.parse_args()
    for name, ms in main(a.weights, 20 if a.quick else a.repeats).items():
        unit = "x" if name.startswith("ratio") else "ms (median)"
        print(f"{name:55s} {ms:8.3f} {unit}")
