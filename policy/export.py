"""Export a trained checkpoint to the weights file of docs/POLICY_SPEC.md.

covey export runs/x/final.pt policy/weights/policy.npz
covey export runs/x/final.pt out.h --format c   # the C header: a format `covey export` adds

This module knows only the npz weights file. Other formats belong to the layers that read them
and reach `cli` as writers (imports run downward: policy never imports what is built on it).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

FormatWriter = Callable[[Path, Path], object]
"""writer(npz_path, out_path): writes the weights file at npz_path to out_path in its format."""


def write_npz(arrays: dict, config: dict, path: str | Path) -> Path:
    """Writes float32 arrays plus the JSON config as a 0-d string array."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}
    out["config"] = np.array(json.dumps(config))
    with open(path, "wb") as f:
        np.savez(f, allow_pickle=True, **out)
    return path


def export_model(model, path: str | Path, extra: dict | None = None) -> Path:
    """Writes an ActorCritic (lstm encoder) as a runtime weights file."""
    from policy.model import state_arrays

    if model.cfg.encoder != "lstm":
        raise ValueError("only the lstm encoder has a runtime weights format")
    config = model.cfg.to_dict()
    config.update(extra or {})
    return write_npz(state_arrays(model), config, path)


def load_checkpoint(path: str | Path):
    """ActorCritic from a trainer checkpoint (.pt)."""
    import torch

    from policy.model import ActorCritic, ModelConfig

    ck = torch.load(path, map_location="cpu", weights_only=False)
    model = ActorCritic(ModelConfig.from_dict(ck["model_cfg"]))
    model.load_state_dict(ck["state_dict"])
    model.eval()
    return model, ck


def parser(formats: Mapping[str, FormatWriter] | None = None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="covey export", description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="trainer checkpoint (.pt) or weights file (.npz)")
    ap.add_argument(
        "out", help="output path (.npz, or the file of another --format, e.g. .h for c)"
    )
    ap.add_argument("--format", choices=("npz", *(formats or {})), default="npz")
    return ap


def cli(argv=None, formats: Mapping[str, FormatWriter] | None = None) -> int:
    """`covey export CHECKPOINT OUT [--format npz|...]`. `formats`: further output formats by
    name, each a writer of the exported npz file (the npz is written beside OUT first)."""
    from cli.options import die

    formats = dict(formats or {})
    if "npz" in formats:
        raise ValueError("the npz format is this module's own; give other formats other names")
    ap = parser(formats)
    args = ap.parse_args(argv)
    src = Path(args.checkpoint)
    if not src.is_file():
        die(ap, f"no such file: {src}")
    if src.suffix == ".npz":
        npz = src
    else:
        model, ck = load_checkpoint(src)
        npz = Path(args.out).with_suffix(".npz") if args.format != "npz" else Path(args.out)
        export_model(model, npz, {"trained_episodes": int(ck.get("episodes", 0))})
    if args.format != "npz":
        formats[args.format](npz, Path(args.out))
    elif npz != Path(args.out):
        Path(args.out).write_bytes(npz.read_bytes())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
