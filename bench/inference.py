"""Policy inference time against the paper's FLOPs and this CPU's measured peak.

    python -m bench.inference [--quick]      # writes inference.json and inference.png

- numpy, one vehicle (`GuidancePolicy.actor.action`: features + LSTM + head) for N = 2..100
  vehicles, i.e. N-1 neighbours, all within the policy's sense range;
- numpy batched: `command_batch` for 1,000 vehicles, nearest 10 (with and without the safety
  filter), and the network alone on the same batch;
- torch batched: the same network in torch on the same batch (skipped without torch);
- C on the host: `firmware.cpolicy.CPolicy.action` through ctypes (N <= 35: the C core takes
  at most 64 reports and feeds at most 40 neighbours).
Anchors: the paper's FLOPs, (N-1) * 34,902 + 17,160, and the peak single-core float32 rate
of this CPU (best of repeated 256x256 matmuls with one BLAS thread).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench import common
from policy.eval import flops as paper_flops
from policy.observation import Observation, Swarm
from policy.runtime import GuidancePolicy

N_VEHICLES = (2, 5, 10, 20, 35, 100)
BATCH_VEHICLES = 1000
BATCH_NEIGHBOURS = 10


def peak_flops(quick: bool) -> dict:
    """Best and median float32 FLOP/s of a 256^3 matmul on one thread (2 n^3 FLOPs)."""
    n = 256
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((n, n), np.float32), rng.standard_normal((n, n), np.float32)
    t = common.time_calls_s(lambda: a @ b, 20 if quick else 60, batch=5, warmup=3)
    rate = 2 * n**3 / t
    return {
        "best_flop_s": float(rate.max()),
        "median_flop_s": float(np.median(rate)),
        "matmul_n": n,
    }


def scatter(rng, k: int, radius_m: float = 18.0):
    """k neighbour positions (policy units) in a disc around the origin and their headings."""
    r = radius_m * np.sqrt(rng.uniform(0.05, 1.0, k))
    th = rng.uniform(-np.pi, np.pi, k)
    return np.stack([r * np.cos(th), r * np.sin(th)], 1), rng.uniform(-np.pi, np.pi, k)


def single(quick: bool, peak: float) -> list[dict]:
    pol = GuidancePolicy.load(safety_filter=False)
    cpol = _cpolicy()
    cfg = pol.config
    rng = np.random.default_rng(1)
    rows = []
    for n in N_VEHICLES:
        nbr, hdg = scatter(rng, n - 1)
        goal = np.array([40.0, 25.0])
        obs = Observation.at_rest(np.zeros(2), 0.3, goal, nbr, hdg)
        t = common.time_calls_s(
            lambda obs=obs: pol.actor.action(obs),
            15 if quick else 100,
            batch=5,
        )
        f_paper = paper_flops(n)
        f_shipped = paper_flops(
            n, h=cfg["hidden"], x=cfg["input"], layers=tuple(cfg["head"][:-1]), a=cfg["head"][-1]
        )
        row = {
            "vehicles": n,
            "neighbours": n - 1,
            "numpy_median_us": float(np.median(t) * 1e6),
            "numpy_min_us": float(t.min() * 1e6),
            "paper_flops": f_paper,
            "shipped_flops": f_shipped,
            "numpy_share_of_peak": f_shipped / float(np.median(t)) / peak,
            "paper_flops_at_peak_us": f_paper / peak * 1e6,
        }
        if cpol is not None and n - 1 <= 64:
            tc = common.time_calls_s(
                lambda obs=obs: cpol.action(obs),
                15 if quick else 100,
                batch=10,
            )
            row["c_median_us"] = float(np.median(tc) * 1e6)
            row["c_min_us"] = float(tc.min() * 1e6)
            row["c_share_of_peak"] = f_shipped / float(np.median(tc)) / peak
        rows.append(row)
        common.say(
            f"N={n:3d}: numpy {row['numpy_median_us']:8.1f} us"
            + (f", C {row['c_median_us']:7.1f} us" if "c_median_us" in row else "")
        )
    return rows


def _cpolicy():
    try:
        from firmware.cpolicy import CPolicy

        return CPolicy.load(policy_separation_m=3.0)  # metres = policy units, as numpy's
    except Exception as exc:  # noqa: BLE001 - no C compiler: the section still runs without C
        common.say(f"C policy unavailable: {exc}")
        return None


def batched(quick: bool, peak: float) -> dict:
    from policy import features

    rng = np.random.default_rng(2)
    n = BATCH_VEHICLES
    side_m = 8.0 * np.sqrt(n)  # about one vehicle per 64 m^2: every vehicle has 10 in range
    pos, goal = rng.uniform(0, side_m, (n, 2)), rng.uniform(0, side_m, (n, 2))
    vel, hdg = rng.normal(0, 0.7, (n, 2)), rng.uniform(-np.pi, np.pi, n)
    reps = 5 if quick else 25
    out = {
        "vehicles": n,
        "nearest": BATCH_NEIGHBOURS,
        "paper_flops": n * paper_flops(BATCH_NEIGHBOURS + 1),
    }
    for filt in (False, True):
        # told the whole 3 m with or without the filter: the same neighbours fed either way
        pol = GuidancePolicy.load(
            safety_filter=filt,
            max_neighbours=BATCH_NEIGHBOURS,
            policy_separation_m=3.0,
            sparse_rule=False,
        )
        swarm = Swarm.checked(pos, vel, hdg, goal)
        t = common.time_calls_s(lambda pol=pol, swarm=swarm: pol.command_batch(swarm), reps)
        out[f"numpy_command_batch_ms{'_filter' if filt else ''}"] = float(np.median(t) * 1e3)
    seq, lengths, goal_feat, _ = features.observe_batch(
        pos, hdg, goal, np.ones(n, bool), pol.obs_cfg, BATCH_NEIGHBOURS
    )
    out["mean_neighbours"] = float(lengths.mean())
    net = pol.net
    t = common.time_calls_s(
        lambda: net.head_forward(net.lstm_last_batch(seq, lengths), goal_feat), reps
    )
    out["numpy_network_ms"] = float(np.median(t) * 1e3)
    cfg = pol.config
    f_net = float(sum(paper_flops(int(k) + 1, h=cfg["hidden"], x=cfg["input"]) for k in lengths))
    out["shipped_flops"] = f_net
    out["numpy_network_share_of_peak"] = f_net / (out["numpy_network_ms"] / 1e3) / peak
    out["per_vehicle_us"] = out["numpy_command_batch_ms"] * 1e3 / n
    out.update(_torch(seq, lengths, goal_feat, reps, f_net, peak))
    common.say(
        f"batch {n}: numpy {out['numpy_command_batch_ms']:.1f} ms, network {out['numpy_network_ms']:.1f} ms, torch {out.get('torch_network_ms', float('nan')):.1f} ms"
    )
    return out


def _torch(seq, lengths, goal_feat, reps: int, f_net: float, peak: float) -> dict:
    try:
        import torch
    except ImportError:
        return {"torch": "not installed"}
    from policy.model import ActorCritic, ModelConfig, load_actor_arrays
    from policy.runtime import DEFAULT_WEIGHTS

    torch.set_num_threads(1)
    with np.load(DEFAULT_WEIGHTS) as z:
        arrays = {k: z[k] for k in z.files}
    model = ActorCritic(ModelConfig.from_dict(json.loads(str(arrays["config"]))))
    load_actor_arrays(model, arrays)
    s = torch.from_numpy(seq.astype(np.float32))
    ln = torch.from_numpy(lengths.astype(np.int64))
    g = torch.from_numpy(goal_feat.astype(np.float32))
    with torch.inference_mode():
        t = common.time_calls_s(lambda: model.actor_mean(s, ln, g), reps)
    ms = float(np.median(t) * 1e3)
    return {
        "torch": torch.__version__,
        "torch_network_ms": ms,
        "torch_network_share_of_peak": f_net / (ms / 1e3) / peak,
    }


def plot(rows: list[dict], peak: float, batch: dict) -> None:
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    n = [r["vehicles"] for r in rows]
    ax.plot(n, [r["numpy_median_us"] for r in rows], "o-", label="numpy, one vehicle")
    c = [r for r in rows if "c_median_us" in r]
    if c:
        ax.plot(
            [r["vehicles"] for r in c],
            [r["c_median_us"] for r in c],
            "s-",
            label="C (host, ctypes)",
        )
    k = batch["nearest"] + 1
    ax.plot(
        [k],
        [batch["per_vehicle_us"]],
        "^",
        color="C2",
        label=f"numpy batched, per vehicle ({batch['vehicles']}, nearest {k - 1})",
    )
    if "torch_network_ms" in batch:
        ax.plot(
            [k],
            [1e3 * batch["torch_network_ms"] / batch["vehicles"]],
            "v",
            color="C3",
            label="torch batched network, per vehicle",
        )
    ax.plot(
        n,
        [r["paper_flops_at_peak_us"] for r in rows],
        "k--",
        label=f"paper FLOPs at peak ({peak / 1e9:.0f} GFLOP/s)",
    )
    ax.set_xlabel("vehicles N (N-1 neighbours)")
    ax.set_ylabel("time per evaluation (us, median)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    common.save_figure(fig, "inference")
    plt.close(fig)


def main(quick: bool = False) -> dict:
    pk = peak_flops(quick)
    common.say(
        f"peak float32 single core: {pk['best_flop_s'] / 1e9:.1f} GFLOP/s (median {pk['median_flop_s'] / 1e9:.1f})"
    )
    peak = pk["best_flop_s"]
    rows = single(quick, peak)
    result = {"quick": quick, "peak": pk, "single": rows, "batch": batched(quick, peak)}
    plot(rows, peak, result["batch"])
    common.write_json("inference", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    main(ap.parse_args().quick)
