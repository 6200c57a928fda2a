"""The shipped weights' training as one command: `covey train --recipe shipped`.

    covey train --recipe shipped --max-minutes 45 --threads 1 --seed 11 --out runs/recipe

Five stages of `policy.train.main`, each started from the weights the one before wrote
(`<out>/<k>-<name>/final.npz`), the last copied to `<out>/final.npz`:

1. from scratch: the improved preset with the continuous collision check (the 36-minute
   one-command run of policy/weights/README.md, 120,000 episodes);
2. the separation filter in the loop at flight's margin, a lone vehicle pulled straight at its
   goal, half of the arenas forced conflicts (issue 16's first fine-tune);
3. the same with the turning penalty at 10;
4. the same with the turning penalty at 14 (issue 16's weights, policy/weights/policy_issue16.npz);
5. the same on drifting position estimates (0.5 m, plain GNSS; collisions judged on the truth,
   the filter inflated as flight's), in metres and told the whole separation, which the
   weights' config then states (`filtered_told_share` 1.0; issue 35, the shipped weights).

Episodes stop each stage, as in the runs that made the shipped weights; `--max-minutes` is
the whole recipe's wall-time budget, split between the stages by `Stage.budget_share`; what a
stage leaves unused (it reached its episodes first) goes to the next, and a stage that reaches
its time first stops early. The recipe sets every
training flag but the ones in RUN_FLAGS.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from policy.train import TrainConfig

RUN_FLAGS = ("out", "seed", "threads", "max_minutes", "progress", "checkpoint_every", "recipe")
"""TrainConfig fields a recipe run takes from the command line; the recipe sets the rest."""


@dataclass(frozen=True)
class Stage:
    """One stage: the TrainConfig fields it sets (on top of TrainConfig's defaults), its episode
    budget and its share of the wall-time budget."""

    name: str
    episodes: int
    budget_share: float
    settings: tuple[tuple[str, object], ...]


_FINE_TUNE = (
    ("safety_filter", True),
    ("lone_anchor", 1.0),
    ("conflict_share", 0.5),
    ("critic_warmup_updates", 15),
    ("lr", 1e-4),
)

_WACC14 = (*_FINE_TUNE, ("w_acc", 14.0), ("init_log_std", -1.3))
_DRIFT = (("drift_m", 0.5), ("told_scale", 1.0), ("filtered_told_share", 1.0))

SHIPPED = (
    Stage("scratch", 120_000, 0.52, (("ccd", True),)),
    Stage("filter", 37_000, 0.12, (*_FINE_TUNE, ("init_log_std", -0.916))),
    Stage("filter-wacc10", 30_000, 0.12, (*_FINE_TUNE, ("w_acc", 10.0), ("init_log_std", -1.2))),
    Stage("filter-wacc14", 30_000, 0.12, _WACC14),
    Stage("drift", 40_000, 0.12, (*_WACC14, *_DRIFT)),
)

RECIPES = {"shipped": SHIPPED}


def stage_configs(cfg: TrainConfig, stages: tuple[Stage, ...]) -> list[TrainConfig]:
    """The TrainConfig of every stage: cfg's run flags (RUN_FLAGS), the stage's settings, a
    seed and a directory of its own, and the weights of the stage before as its --init."""
    out = Path(cfg.out)
    per_stage = ("recipe", "seed", "max_minutes")  # set per stage below
    run = {name: getattr(cfg, name) for name in RUN_FLAGS if name not in per_stage}
    configs: list[TrainConfig] = []
    for k, stage in enumerate(stages, start=1):
        over: dict[str, Any] = dict(stage.settings)
        over.update(
            run,
            out=str(out / f"{k}-{stage.name}"),
            seed=cfg.seed + k - 1,
            episodes=stage.episodes,
            max_minutes=cfg.max_minutes * stage.budget_share,
            init=str(Path(configs[-1].out) / "final.npz") if configs else "",
        )
        configs.append(replace(TrainConfig(), **over))
    return configs


def run(
    cfg: TrainConfig,
    stages: tuple[Stage, ...] | None = None,
    clock_s: Callable[[], float] = time.monotonic,
) -> dict:
    """Trains every stage in turn; writes <out>/final.npz; returns the last stage's last row
    with the stages' rows under "stages". `clock_s` times the stages (for the carried-over
    budget)."""
    from policy import train

    stages = RECIPES[cfg.recipe] if stages is None else stages
    rows = []
    spare_min = 0.0  # budget the stages before left unused (they stopped by their episodes)
    for stage, stage_cfg in zip(stages, stage_configs(cfg, stages), strict=True):
        if cfg.max_minutes:
            stage_cfg = replace(stage_cfg, max_minutes=stage_cfg.max_minutes + spare_min)
        t0 = clock_s()
        row = train.main(stage_cfg)
        if cfg.max_minutes:
            spare_min = max(0.0, stage_cfg.max_minutes - (clock_s() - t0) / 60.0)
        rows.append({"stage": stage.name, "out": stage_cfg.out, **row})
        print(
            f"covey train --recipe {cfg.recipe}: stage {stage.name}: "
            f"{row.get('episodes', 0):,} episodes in {row.get('wall_s', 0.0) / 60:.1f} min "
            f"(budget {stage_cfg.episodes:,} episodes, {stage_cfg.max_minutes:.1f} min)",
            flush=True,
        )
    shutil.copyfile(Path(rows[-1]["out"]) / "final.npz", Path(cfg.out) / "final.npz")
    return {**rows[-1], "stages": rows}
