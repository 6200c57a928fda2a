"""`covey train`: the trainer's command line (policy/train.py), one flag per TrainConfig field;
`--recipe` runs a staged recipe (policy/recipe.py) instead of one run."""

from __future__ import annotations

import argparse
from typing import Any

from policy.train import TrainConfig, main


def parser() -> argparse.ArgumentParser:
    """One flag per TrainConfig field (help: the docstring under it), plus --episodes-k."""
    from cli.options import add_config_flags, finite

    ap = argparse.ArgumentParser(
        prog="covey train", description="Train the guidance policy with PPO."
    )
    add_config_flags(ap, TrainConfig, types={"max_minutes": finite("minutes", inclusive=True)})
    ap.add_argument(
        "--episodes-k",
        type=finite("thousand episodes"),
        default=None,
        help="episodes in thousands (overrides --episodes)",
    )
    return ap


def cli(argv=None) -> dict:
    """`covey train [--field value ...]`: one flag per TrainConfig field."""
    from cli.options import config_from_flags, given

    ap = parser()
    args = ap.parse_args(argv)
    if args.episodes_k is not None and given(ap, args, "episodes"):
        ap.error("--episodes and --episodes-k say the same thing: give one")
    over: dict[str, Any] = (
        {} if args.episodes_k is None else {"episodes": int(args.episodes_k * 1000)}
    )
    cfg = config_from_flags(TrainConfig, args, **over)
    if cfg.recipe:
        from policy import recipe

        if cfg.recipe not in recipe.RECIPES:
            ap.error(f"--recipe must be one of {', '.join(recipe.RECIPES)}, got {cfg.recipe!r}")
        clash = given(ap, args, *(f for f in vars(args) if f not in recipe.RUN_FLAGS))
        if clash:
            ap.error(f"--recipe {cfg.recipe} sets {', '.join(clash)} itself; leave them out")
        last = recipe.run(cfg)
        print(
            f"covey train --recipe {cfg.recipe}: {len(last['stages'])} stages in "
            f"{sum(r.get('wall_s', 0.0) for r in last['stages']) / 60:.1f} min; wrote {cfg.out}/final.npz"
        )
        return last
    if cfg.preset not in ("paper", "improved"):
        ap.error(f"--preset must be paper or improved, got {cfg.preset!r}")
    from policy.env import EnvConfig

    if cfg.filtered_told_share is not None:
        from policy.runtime import TOLD_SHARE_KEY, config_told_share

        try:
            config_told_share({TOLD_SHARE_KEY: cfg.filtered_told_share}, "--filtered-told-share")
        except ValueError as exc:
            ap.error(str(exc))
    for field in ("filter_margin", "drift_m", "drift_corr_s", "told_scale"):
        try:  # the environment's own check, said as the flag
            EnvConfig(**{field: getattr(cfg, field)})
        except ValueError as exc:
            ap.error(f"--{field.replace('_', '-')}: {exc}")
    if cfg.encoder not in ("lstm", "occupancy"):
        ap.error(f"--encoder must be lstm or occupancy, got {cfg.encoder!r}")
    last = main(cfg)
    print(
        f"covey train: {last.get('episodes', 0):,} episodes in {last.get('wall_s', 0.0) / 60:.1f} min; "
        f"last success {last.get('success', float('nan')):.3f}, collision {last.get('collision', float('nan')):.3f}; "
        f"wrote {cfg.out}/ (final.npz, final.pt, log.csv, curve.png)"
    )
    return last


if __name__ == "__main__":
    cli()
