"""PPO trainer for the guidance policy, CleanRL style: read it top to bottom.

Every vehicle of every arena is one agent of a shared policy; all active agents go
through one batched forward pass per step, and each vehicle's experience is its own
trajectory (GAE cut where it leaves). Writes checkpoints, a CSV log, the exported
weights (`final.npz`) and the training curve (`curve.png`, as the paper's Fig. 4a).

    covey train --preset improved --episodes 100000 --out runs/improved
"""

from __future__ import annotations

import csv
import math
import os
import time
from collections import deque
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from policy.safety import SafetyConfig


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on; `main(cfg)` is the whole trainer."""

    preset: str = "improved"
    """Network/observation preset: "paper" or "improved" (see policy.model.PRESETS)."""
    encoder: str = "lstm"
    """"lstm" or "occupancy" (the paper's baseline; not exportable to the runtime)."""
    episodes: int = 100_000
    """Stop after this many finished arenas (the paper's budget is 100,000)."""
    max_minutes: float = 0.0
    """Also stop after this wall time (0 = no limit)."""
    seed: int = 1
    """Seeds the environment, torch and the action noise."""
    num_envs: int = 128
    """Arenas per rollout."""
    num_steps: int = 32
    """Steps per rollout and arena."""
    lr: float = 3e-4
    """Adam learning rate (annealed linearly to 10 % over the episode budget)."""
    gamma: float = 0.99
    """Discount."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    update_epochs: int = 4
    """PPO epochs per rollout."""
    minibatch_size: int = 2048
    """Samples (agent steps) per minibatch."""
    clip_coef: float = 0.2
    """PPO ratio clip."""
    vf_coef: float = 0.5
    """Value loss weight."""
    ent_coef: float = 0.0
    """Entropy bonus."""
    max_grad_norm: float = 0.5
    """Gradient norm clip."""
    init_log_std: float = math.log(0.6)
    """Initial action noise (the code used a fixed std 0.6)."""
    reward_scale: float = 0.01
    """Rewards are multiplied by this for learning (the log shows raw rewards)."""
    max_vehicles: int = 5
    """Vehicle-count cap in training."""
    w_acc: float = 6.0
    """Weight of the acceleration term."""
    w_tme: float = 1.5
    """Weight of the time term."""
    w_prog: float = 10.0
    """Weight of the progress shaping term (0 = the paper's reward)."""
    ccd: bool = True
    """Check collisions along each 1 s step, not only at its end (see EnvConfig.ccd)."""
    conflict_share: float = 0.0
    """Share of arenas drawn as forced conflicts (EnvConfig.conflict_share)."""
    safety_filter: bool = False
    """Fly the actions through the separation filter, as flight does (EnvConfig.safety_filter)."""
    filter_margin: float = SafetyConfig.margin
    """With --safety-filter: the filter's relative padding on the separation
    (EnvConfig.filter_margin; flight's policy.safety.SafetyConfig.margin, 0.1 before issue 16)."""
    delta_cav_m: float = 10.0
    """The proximity penalty R_CAV starts this close (the paper: 10 m; see EnvConfig)."""
    knee_cav_m: float = 6.0
    """R_CAV turns quadratic this close (the paper: 6 m)."""
    drift_m: float = 0.0
    """Each vehicle's position estimate drifts from the truth by this 1-sigma per axis
    (EnvConfig.drift_m; 0.5 is plain GNSS in metres); collisions are judged on the truth."""
    drift_corr_s: float = 10.0
    """Correlation time of that drift (EnvConfig.drift_corr_s)."""
    told_scale: float = 1.0
    """The network sees the arena this many times larger (EnvConfig.told_scale; 2.4 is how
    flight tells the legacy weights 3 m with the filter on)."""
    filtered_told_share: float | None = None
    """Written into the weights' config: the share of the separation flight tells them with the
    filter on (policy.runtime.filtered_told_share); state the geometry trained in, e.g. 1.0 for
    an arena in metres told the whole separation. None: not written (flight then tells
    LEGACY_FILTERED_TOLD_SHARE, 1.25 / 3)."""
    lone_anchor: float = 0.0
    """Weight of a loss pulling the action of a vehicle with no neighbour in sense range to
    full speed straight at its goal (the closed-form optimum there); 0 = off. The target is
    LONE_TARGET_NORM long and compared with the unit-clipped action, so that the tanh output
    saturates at full speed instead of creeping towards it."""
    init: str = ""
    """Start from this trainer checkpoint (.pt) or weights file (.npz, actor only; the critic
    starts fresh and learns alone for `critic_warmup_updates`) instead of fresh weights."""
    critic_warmup_updates: int = 0
    """Updates at the start that train only the value head (for an --init from weights)."""
    fwd_bias: float = 0.5
    """Initial bias of the forward output, so that vehicles start by flying forward."""
    threads: int = 2
    """torch threads."""
    out: str = "runs/train"
    """Run directory: checkpoints, log.csv, final.npz, curve.png."""
    checkpoint_every: int = 50
    """Updates between checkpoints."""
    progress: bool = True
    """Show a tqdm bar."""
    recipe: str = ""
    """Run a whole multi-stage recipe instead of one stage: "shipped" trains the shipped
    weights' way from scratch (policy.recipe); it sets every other training flag, and
    --max-minutes is then the budget of all its stages together."""


def main(cfg: TrainConfig) -> dict:
    """Trains, writes the run directory, returns the last logged row."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch
    from tqdm import tqdm

    from policy.env import EnvConfig, SwarmEnv
    from policy.export import export_model
    from policy.model import PRESETS, ActorCritic, clip_unit, parameter
    from policy.runtime import TOLD_SHARE_KEY, config_told_share

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    model_cfg = replace(PRESETS[cfg.preset], encoder=cfg.encoder)
    env_cfg = EnvConfig(
        num_envs=cfg.num_envs,
        max_vehicles=cfg.max_vehicles,
        w_acc=cfg.w_acc,
        w_tme=cfg.w_tme,
        w_prog=cfg.w_prog,
        ccd=cfg.ccd,
        safety_filter=cfg.safety_filter,
        filter_margin=cfg.filter_margin,
        conflict_share=cfg.conflict_share,
        delta_cav_m=cfg.delta_cav_m,
        knee_cav_m=cfg.knee_cav_m,
        drift_m=cfg.drift_m,
        drift_corr_s=cfg.drift_corr_s,
        told_scale=cfg.told_scale,
    )
    env = SwarmEnv(env_cfg, model_cfg.obs)
    told = {}
    if cfg.filtered_told_share is not None:
        told = {TOLD_SHARE_KEY: config_told_share({TOLD_SHARE_KEY: cfg.filtered_told_share})}
    model = ActorCritic(model_cfg, cfg.init_log_std)
    with torch.no_grad():
        parameter(model.head[-1], "bias")[0] = cfg.fwd_bias
    if cfg.init.endswith(".npz"):
        load_actor(model, cfg.init)
    elif cfg.init:
        ck = torch.load(cfg.init, map_location="cpu", weights_only=False)
        if ck["model_cfg"] != model_cfg.to_dict():
            raise ValueError(
                f"--init {cfg.init} has model config {ck['model_cfg']}, not {model_cfg.to_dict()}"
            )
        model.load_state_dict(ck["state_dict"])
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr, eps=1e-5)

    t_n, e_n, m_n = cfg.num_steps, cfg.num_envs, cfg.max_vehicles
    k_n, x_n, g_n = m_n - 1, model_cfg.obs.input_size, model_cfg.obs.goal_size
    seq_buf = np.zeros((t_n, e_n, m_n, k_n, x_n), np.float32)
    len_buf = np.zeros((t_n, e_n, m_n), np.int64)
    goal_buf = np.zeros((t_n, e_n, m_n, g_n), np.float32)
    act_buf = np.zeros((t_n, e_n, m_n, 2), np.float32)
    logp_buf = np.zeros((t_n, e_n, m_n), np.float32)
    val_buf = np.zeros((t_n, e_n, m_n), np.float32)
    rew_buf = np.zeros((t_n, e_n, m_n), np.float32)
    done_buf = np.zeros((t_n, e_n, m_n), np.float32)
    mask_buf = np.zeros((t_n, e_n, m_n), bool)
    straight_buf = np.zeros((t_n, e_n, m_n, 2), np.float32)

    def policy_step(seq, lengths, goal):
        with torch.no_grad():
            mean, value = model(
                torch.from_numpy(seq), torch.from_numpy(lengths), torch.from_numpy(goal)
            )
            std = model.log_std.exp()
            a = mean + std * torch.randn_like(mean)
            logp = torch.distributions.Normal(mean, std).log_prob(a).sum(-1)
        return a.numpy(), logp.numpy(), value.numpy()

    obs = env.reset(cfg.seed)
    recent: deque = deque(maxlen=500)
    episodes, update, t0 = 0, 0, time.time()
    log_path = out / "log.csv"
    log_f = open(log_path, "w", newline="")  # noqa: SIM115 - closed below; a with-block would indent the whole loop
    writer = None
    row: dict = {}
    bar = tqdm(total=cfg.episodes, disable=not cfg.progress, unit="ep", smoothing=0.05)
    while episodes < cfg.episodes and not (
        cfg.max_minutes and time.time() - t0 > 60 * cfg.max_minutes
    ):
        frac = min(episodes / cfg.episodes, 1.0)
        optim.param_groups[0]["lr"] = cfg.lr * (1.0 - 0.9 * frac)
        # ---- rollout ----
        for t in range(t_n):
            seq, lengths, goal = obs
            mask = env.active.copy()
            seq_buf[t], len_buf[t], goal_buf[t], mask_buf[t] = seq, lengths, goal, mask
            straight_buf[t] = straight_action(env.pos, env.heading, env.goal, LONE_TARGET_NORM)
            a, logp, value = policy_step(
                seq[mask].astype(np.float32), lengths[mask], goal[mask].astype(np.float32)
            )
            actions = np.zeros((e_n, m_n, 2))
            actions[mask] = a
            act_buf[t][mask], logp_buf[t][mask], val_buf[t][mask] = a, logp, value
            val_buf[t][~mask] = 0.0
            reward, done, info = env.step(actions)
            rew_buf[t] = reward * cfg.reward_scale
            done_buf[t] = done | ~mask
            if info["env_done"].any():
                for ret, ok, col in env.episode_stats(info["env_done"]):
                    recent.append((ret, ok, col))
                n_done = int(info["env_done"].sum())
                episodes += n_done
                bar.update(n_done)
                env.reset_envs(info["env_done"])
            obs = env.observe()
        # ---- GAE, cut where a vehicle leaves (or its slot is empty) ----
        seq, lengths, goal = obs
        mask = env.active
        next_val = np.zeros((e_n, m_n), np.float32)
        if mask.any():
            _, _, v = policy_step(
                seq[mask].astype(np.float32), lengths[mask], goal[mask].astype(np.float32)
            )
            next_val[mask] = v
        adv = np.zeros_like(rew_buf)
        last = np.zeros((e_n, m_n), np.float32)
        for t in reversed(range(t_n)):
            nv = next_val if t == t_n - 1 else val_buf[t + 1]
            nonterm = 1.0 - done_buf[t]
            delta = rew_buf[t] + cfg.gamma * nv * nonterm - val_buf[t]
            last = delta + cfg.gamma * cfg.gae_lambda * nonterm * last
            adv[t] = last
        ret = adv + val_buf
        # ---- PPO update on the active samples ----
        b = mask_buf
        b_seq = torch.from_numpy(seq_buf[b])
        b_len = torch.from_numpy(len_buf[b])
        b_goal = torch.from_numpy(goal_buf[b])
        b_act = torch.from_numpy(act_buf[b])
        b_logp = torch.from_numpy(logp_buf[b])
        b_adv = torch.from_numpy(adv[b])
        b_ret = torch.from_numpy(ret[b])
        b_val = torch.from_numpy(val_buf[b])
        b_straight = torch.from_numpy(straight_buf[b])
        b_lone = b_len == 0
        actor_on = update >= cfg.critic_warmup_updates
        n = b_seq.shape[0]
        stats = []
        # advantages normalised over the whole batch: a per-minibatch std is NaN for a
        # minibatch of one sample (this once turned every weight into NaN)
        adv_mean, adv_std = b_adv.mean(), b_adv.std() + 1e-8
        for _ in range(cfg.update_epochs):
            perm = torch.randperm(n)
            for s in range(0, n, cfg.minibatch_size):
                mb = perm[s : s + cfg.minibatch_size]
                if mb.numel() < 2:
                    continue
                mean, value = model(b_seq[mb], b_len[mb], b_goal[mb])
                dist = torch.distributions.Normal(mean, model.log_std.exp())
                logp = dist.log_prob(b_act[mb]).sum(-1)
                ratio = (logp - b_logp[mb]).exp()
                mb_adv = (b_adv[mb] - adv_mean) / adv_std
                pg_loss = torch.max(
                    -mb_adv * ratio, -mb_adv * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)
                ).mean()
                v_clip = b_val[mb] + (value - b_val[mb]).clamp(
                    -cfg.clip_coef * 10, cfg.clip_coef * 10
                )
                v_loss = 0.5 * torch.max((value - b_ret[mb]) ** 2, (v_clip - b_ret[mb]) ** 2).mean()
                ent = dist.entropy().sum(-1).mean()
                loss = cfg.vf_coef * v_loss
                if actor_on:
                    loss = loss + pg_loss - cfg.ent_coef * ent
                    lone = b_lone[mb]
                    if cfg.lone_anchor > 0 and bool(lone.any()):
                        miss = ((clip_unit(mean[lone]) - b_straight[mb][lone]) ** 2).sum(-1).mean()
                        loss = loss + cfg.lone_anchor * miss
                if not torch.isfinite(loss):
                    raise FloatingPointError(
                        f"non-finite loss at update {update}; last checkpoint is intact"
                    )
                optim.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
                optim.step()
                with torch.no_grad():
                    clipfrac = ((ratio - 1).abs() > cfg.clip_coef).float().mean()
                stats.append((pg_loss.item(), v_loss.item(), clipfrac.item()))
        update += 1
        # ---- log ----
        if recent:
            r = np.array(recent, dtype=np.float64)
            pg, vl, cf = np.mean(stats, axis=0)
            row = {
                "update": update,
                "episodes": episodes,
                "wall_s": round(time.time() - t0, 1),
                "reward": round(float(r[:, 0].mean()), 2),
                "success": round(float(r[:, 1].mean()), 4),
                "collision": round(float(r[:, 2].mean()), 4),
                "pg_loss": round(float(pg), 5),
                "v_loss": round(float(vl), 5),
                "clipfrac": round(float(cf), 4),
                "std": round(float(model.log_std.detach().exp().mean()), 4),
                "samples": n,
            }
            if writer is None:
                writer = csv.DictWriter(log_f, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            log_f.flush()
            bar.set_postfix(rew=row["reward"], succ=row["success"], coll=row["collision"])
        if update % cfg.checkpoint_every == 0:
            _save(model, optim, cfg, episodes, out / "checkpoint.pt")
            if model_cfg.encoder == "lstm":
                export_model(model, out / "checkpoint.npz", {"trained_episodes": episodes, **told})
    bar.close()
    log_f.close()
    _save(model, optim, cfg, episodes, out / "final.pt")
    if model_cfg.encoder == "lstm":
        export_model(model, out / "final.npz", {"trained_episodes": episodes, **told})
    plot_curve(log_path, out / "curve.png")
    return row


LONE_TARGET_NORM = 1.1
"""Length of the lone-vehicle target action (TrainConfig.lone_anchor); the clipped action can
only reach length 1, so the loss keeps pushing a tanh output that has not saturated."""


def straight_action(pos, heading_rad, goal, norm: float = 1.0):
    """Body-frame action (fwd, right) straight at the goal, `norm` long, (..., 2) float32:
    what a vehicle with no one to avoid should fly (full speed, no turn after the first)."""
    gd = goal - pos
    b = np.arctan2(gd[..., 1], gd[..., 0]) - heading_rad
    return (norm * np.stack([np.cos(b), np.sin(b)], -1)).astype(np.float32)


def load_actor(model, path: str) -> None:
    """Actor weights (LSTM and head) from a runtime weights file into `model`; its config must
    match. The critic and the action noise keep their fresh values."""
    import json

    from policy.model import load_actor_arrays

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    have = {k: v for k, v in json.loads(str(arrays["config"])).items() if k != "trained_episodes"}
    want = model.cfg.to_dict()
    if {k: have.get(k) for k in want} != want:
        raise ValueError(f"--init {path} has model config {have}, not {want}")
    load_actor_arrays(model, arrays)


def _save(model, optim, cfg: TrainConfig, episodes: int, path: Path) -> None:
    import torch

    torch.save(
        {
            "state_dict": model.state_dict(),
            "optim": optim.state_dict(),
            "model_cfg": model.cfg.to_dict(),
            "train_cfg": asdict(cfg),
            "episodes": episodes,
        },
        path,
    )


def plot_curve(log_csv: Path, png: Path) -> None:
    """Reward and success rate against episodes (like the paper's Fig. 4a)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(log_csv) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    ep = [int(r["episodes"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(ep, [float(r["reward"]) for r in rows], color="C0")
    ax.set_xlabel("episodes")
    ax.set_ylabel("mean vehicle return (500 arenas)", color="C0")
    ax2 = ax.twinx()
    ax2.plot(ep, [float(r["success"]) for r in rows], color="C1")
    ax2.plot(ep, [float(r["collision"]) for r in rows], color="C3", ls="--")
    ax2.set_ylabel("success (solid) / collision (dashed)")
    ax2.set_ylim(0, 1)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)
