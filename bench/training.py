"""Training throughput, and what the shipped policy cost to train.

    python -m bench.training [--quick]       # writes training.json (and training.png)

- env steps/s of the vectorized environment (`policy.env.SwarmEnv`, 128 arenas, random
  actions): arena-steps and vehicle-steps per second;
- PPO samples/s of the real trainer (`policy.train.main`, a short run in a temporary folder,
  one torch thread); skipped without torch;
- wall time to the shipped quality, read from the shipped training log
  (policy/weights/*.csv, the trainer's log.csv format) or policy/weights/README.md, never by
  retraining; and the training curve (reward and success against episodes, as the paper's
  Fig. 4a) when the log is there.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import common
from policy.runtime import DEFAULT_WEIGHTS

WEIGHTS_DIR = DEFAULT_WEIGHTS.parent


def env_steps(quick: bool) -> dict:
    from policy.env import EnvConfig, SwarmEnv
    from policy.features import ObsConfig

    with np.load(DEFAULT_WEIGHTS) as z:
        obs_cfg = ObsConfig.from_dict(json.loads(str(z["config"])))
    env = SwarmEnv(EnvConfig(num_envs=128), obs_cfg)
    env.reset(0)
    rng = np.random.default_rng(0)
    arena_steps = vehicle_steps = 0
    budget_s = 1.0 if quick else 8.0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < budget_s:
        env.observe()  # the trainer observes every step
        vehicle_steps += int(env.active.sum())
        _, _, info = env.step(rng.uniform(-1, 1, (*env.active.shape, 2)))
        arena_steps += env.cfg.num_envs
        if info["env_done"].any():
            env.reset_envs(info["env_done"])
    wall_s = time.perf_counter() - t0
    return {
        "num_envs": env.cfg.num_envs,
        "arena_steps_s": arena_steps / wall_s,
        "vehicle_steps_s": vehicle_steps / wall_s,
    }


def ppo(quick: bool) -> dict:
    try:
        import torch  # noqa: F401
    except ImportError:
        return {"skipped": "torch is not installed"}
    from policy.train import TrainConfig
    from policy.train import main as train

    with np.load(DEFAULT_WEIGHTS) as z:
        preset = "improved" if json.loads(str(z["config"])).get("encoding") == "sincos" else "paper"
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(
            preset=preset,
            episodes=10**9,
            max_minutes=0.08 if quick else 1.5,
            threads=1,
            out=tmp,
            progress=False,
            checkpoint_every=10**6,
            **({"num_envs": 32, "num_steps": 16} if quick else {}),
        )
        t0 = time.perf_counter()
        train(cfg)
        total_s = time.perf_counter() - t0
        with open(Path(tmp) / "log.csv") as f:
            rows = list(csv.DictReader(f))
    if not rows:
        return {"skipped": "the trainer logged no update"}
    wall_s = float(rows[-1]["wall_s"])
    samples = sum(int(r["samples"]) for r in rows)
    episodes = int(rows[-1]["episodes"])
    return {
        "preset": preset,
        "num_envs": cfg.num_envs,
        "num_steps": cfg.num_steps,
        "torch_threads": cfg.threads,
        "updates": len(rows),
        "samples": samples,
        "episodes": episodes,
        "wall_s": wall_s,
        "samples_s": samples / wall_s,
        "episodes_s": episodes / wall_s,
        "run_with_setup_s": total_s,
    }


def shipped_log() -> tuple[Path | None, list[dict]]:
    """The shipped training log (the trainer's CSV columns): a CSV shipped beside the weights,
    else the log.csv files of the run directories that policy/weights/README.md names
    (`--out DIR`, in order: a staged run is fine-tuned from the previous stage), joined with
    episodes and wall time carried over, if those runs are still on this machine."""

    def read(path: Path) -> list[dict]:
        with open(path) as f:
            rows = list(csv.DictReader(f))
        ok = rows and {"episodes", "wall_s", "reward", "success"} <= set(rows[0])
        return [r for r in rows if np.isfinite(float(r["reward"]))] if ok else []

    for path in sorted(WEIGHTS_DIR.glob("*.csv")):
        if rows := read(path):
            return path, rows
    readme = WEIGHTS_DIR / "README.md"
    if not readme.is_file():
        return None, []
    dirs = list(dict.fromkeys(re.findall(r"--out\s+(\S+)", readme.read_text())))
    joined: list[dict] = []
    first = None
    for d in dirs:
        path = common.REPO / d / "log.csv"
        rows = read(path) if path.is_file() else []
        if not rows:
            continue
        first = first or path
        ep0 = float(joined[-1]["episodes"]) if joined else 0.0
        wall0 = float(joined[-1]["wall_s"]) if joined else 0.0
        for r in rows:
            joined.append(
                {
                    **r,
                    "episodes": float(r["episodes"]) + ep0,
                    "wall_s": float(r["wall_s"]) + wall0,
                    "stage": d,
                    "stage_episodes": r["episodes"],
                }
            )
    return first, joined


def shipped_quality(ppo_result: dict) -> dict:
    with np.load(DEFAULT_WEIGHTS) as z:
        cfg = json.loads(str(z["config"]))
    out: dict = {
        "weights": str(DEFAULT_WEIGHTS.relative_to(common.REPO)),
        "trained_episodes": cfg.get("trained_episodes"),
    }
    path, rows = shipped_log()
    if rows:
        ep = np.array([float(r["episodes"]) for r in rows])
        wall = np.array([float(r["wall_s"]) for r in rows])
        succ = np.array([float(r["success"]) for r in rows])
        final = float(np.mean(succ[-5:]))
        reach = int(np.argmax(succ >= 0.95 * final))
        rew = np.array([float(r["reward"]) for r in rows])
        final_rew = float(np.mean(rew[-5:]))
        reach_rew = int(np.argmax(rew >= final_rew - 0.05 * abs(final_rew)))
        out.update(
            {
                "log": ", ".join(
                    dict.fromkeys(r.get("stage", str(path.relative_to(common.REPO))) for r in rows)
                ),
                "log_episodes": int(ep[-1]),
                "log_wall_s": float(wall[-1]),
                "final_success": final,
                "final_reward": final_rew,
                "wall_s_to_95pct_of_final_success": float(wall[reach]),
                "episodes_to_95pct_of_final_success": int(ep[reach]),
                "wall_s_to_95pct_of_final_reward": float(wall[reach_rew]),
                "episodes_to_95pct_of_final_reward": int(ep[reach_rew]),
                "log_matches_weights": out["trained_episodes"]
                in (int(ep[-1]), int(float(rows[-1].get("stage_episodes", ep[-1])))),
                "log_in_git": WEIGHTS_DIR in path.parents,
            }
        )
    readme = WEIGHTS_DIR / "README.md"
    if readme.is_file():
        lines = [ln.strip() for ln in readme.read_text().splitlines()]
        out["readme_lines"] = [
            ln for ln in lines if re.search(r"\b(wall|minutes?|hours?|min\b|episodes/s)", ln, re.I)
        ][:8]
    if "log_wall_s" not in out and out["trained_episodes"] and ppo_result.get("episodes_s"):
        out["estimated_wall_s"] = out["trained_episodes"] / ppo_result["episodes_s"]
        out["estimate_note"] = (
            "no shipped training log: trained_episodes / PPO episodes/s measured here"
        )
    return out


def plot(rows: list[dict]) -> None:
    plt = common.pyplot()
    ep = [float(r["episodes"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.4))
    ax.plot(ep, [float(r["reward"]) for r in rows], color="C0")
    ax.set_xlabel("episodes")
    ax.set_ylabel("mean vehicle return", color="C0")
    ax2 = ax.twinx()
    ax2.plot(ep, [float(r["success"]) for r in rows], color="C1", label="success")
    if "collision" in rows[0]:
        ax2.plot(ep, [float(r["collision"]) for r in rows], color="C3", ls="--", label="collision")
    for k in range(1, len(rows)):  # fine-tuning stages (e.g. with the continuous collision check)
        if rows[k].get("stage") != rows[k - 1].get("stage"):
            ax.axvline(float(rows[k]["episodes"]), color="grey", lw=0.8, ls=":")
    ax2.set_ylim(0, 1)
    ax2.set_ylabel("share of vehicles")
    ax2.legend(loc="center right", fontsize=8)
    ax.set_title("shipped policy: training curve (cf. paper Fig. 4a)", fontsize=9)
    fig.tight_layout()
    common.save_figure(fig, "training")
    plt.close(fig)


def main(quick: bool = False) -> dict:
    env = env_steps(quick)
    common.say(
        f"env: {env['arena_steps_s']:,.0f} arena-steps/s, {env['vehicle_steps_s']:,.0f} vehicle-steps/s"
    )
    p = ppo(quick)
    if "samples_s" in p:
        common.say(
            f"PPO: {p['samples_s']:,.0f} samples/s, {p['episodes_s']:.1f} episodes/s over {p['wall_s']:.0f} s"
        )
    q = shipped_quality(p)
    _, rows = shipped_log()
    if rows:
        plot(rows)
    result = {"quick": quick, "env": env, "ppo": p, "shipped": q}
    common.write_json("training", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    main(ap.parse_args().quick)
