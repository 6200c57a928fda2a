"""Export a trained checkpoint to the weights file of docs/POLICY_SPEC.md.

covey export runs/x/final.pt policy/weights/policy.npz
covey export runs/x/final.pt out.h --format c   # needs firmware's export_c_header
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def write_npz(arrays: dict, config: dict, path: str | Path) -> Path:
    """Writes float32 arrays plus the JSON config as a 0-d string array."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}
    out["config"] = np.array(json.dumps(config))
    with open(path, "wb") as f:
        np.savez(f, **out)
    return path


def export_model(model, path: str | Path, extra: dict | None = None) -> Path:
    """Writes an ActorCritic (lstm encoder) as a runtime weights file."""
    from policy.model import state_arrays

    if model.cfg.encoder != "lstm":
        raise ValueError("only the lstm encoder has a runtime/firmware format")
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


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="covey export", description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="trainer checkpoint (.pt) or weights file (.npz)")
    ap.add_argument("out", help="output path (.npz, or .h with --format c)")
    ap.add_argument("--format", choices=("npz", "c"), default="npz")
    return ap


def cli(argv=None) -> int:
    """`covey export CHECKPOINT OUT [--format npz|c]`."""
    from comms.cli_options import die

    ap = parser()
    args = ap.parse_args(argv)
    src = Path(args.checkpoint)
    if not src.is_file():
        die(ap, f"no such file: {src}")
    if src.suffix == ".npz":
        npz = src
    else:
        model, ck = load_checkpoint(src)
        npz = Path(args.out).with_suffix(".npz") if args.format == "c" else Path(args.out)
        export_model(model, npz, {"trained_episodes": int(ck.get("episodes", 0))})
    if args.format == "c":
        try:
            from firmware.export_c import export_c_header  # owned by firmware/
        except ImportError as e:
            die(ap, f"--format c needs firmware.export_c.export_c_header: {e}")
        export_c_header(str(npz), args.out)
    elif npz != Path(args.out):
        Path(args.out).write_bytes(npz.read_bytes())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
