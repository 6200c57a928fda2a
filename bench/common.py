"""What every benchmark section shares: machine facts, timing, child processes, output.

The BLAS environment (one thread, passive waits) is set by bench/__init__.py, which Python
imports before this module and before numpy.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from kit.procs import Child, ChildExited, ChildGroup, python_env

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
RESULTS = BENCH / "results"
DOCS = REPO / "docs"
OUT_ENV = "COVEY_BENCH_OUT"
"""The runner tells a section where to write through this variable (default bench/results)."""


def out_dir() -> Path:
    d = Path(os.environ.get(OUT_ENV, RESULTS))
    d.mkdir(parents=True, exist_ok=True)
    return d


def machine() -> dict:
    """Facts that make numbers comparable: CPU, cores, load average now, versions."""
    model = ""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    load1, load5, load15 = os.getloadavg()
    return {
        "cpu": model or platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "loadavg_1_5_15": [round(load1, 2), round(load5, 2), round(load15, 2)],
        "python": platform.python_version(),
        "numpy": np.__version__,
        "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def time_calls_s(
    fn: Callable[[], object], repeats: int, batch: int = 1, warmup: int = 2
) -> np.ndarray:
    """Seconds per call of `fn`, one entry per timed batch of `batch` calls."""
    for _ in range(warmup):
        fn()
    out = np.empty(repeats)
    for r in range(repeats):
        t0 = time.perf_counter()
        for _ in range(batch):
            fn()
        out[r] = (time.perf_counter() - t0) / batch
    return out


def pct(values, q: float) -> float:
    """Percentile q (0-100) of `values`, NaN when empty."""
    v = np.asarray(values, dtype=float)
    return float(np.percentile(v, q)) if v.size else float("nan")


def write_json(name: str, result: dict) -> Path:
    """bench/results/<name>.json (or the runner's output folder), with machine facts added."""
    result = {"section": name, "machine": machine(), **result}
    path = out_dir() / f"{name}.json"
    path.write_text(json.dumps(result, indent=2, default=float) + "\n")
    return path


def save_figure(fig, name: str) -> list[Path]:
    """Save a matplotlib figure as <name>.png in the output folder, and under docs/ when the
    output folder is bench/results (a test run must not overwrite the docs)."""
    paths = [out_dir() / f"{name}.png"]
    if out_dir().resolve() == RESULTS.resolve():
        paths.append(DOCS / f"bench_{name}.png")
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(p, dpi=80)
    return paths


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def say(text: str) -> None:
    """Progress goes to stderr so that stdout stays machine-readable."""
    print(f"  {time.strftime('%H:%M:%S')} {text}", file=sys.stderr, flush=True)


def add_eval_flags(ap, seeds: str, suites: str, reuse_help: str) -> None:
    """--seeds, --suites and --reuse of a bench that flies `covey eval` runs (`eval_flags`)."""
    ap.add_argument("--seeds", default=seeds, help="comma list of covey eval seeds")
    ap.add_argument("--suites", default=suites, help="covey eval suites")
    ap.add_argument("--reuse", action="store_true", help=reuse_help)


def eval_flags(args) -> tuple[list[int], tuple[str, ...]]:
    """(seeds, suites) from `add_eval_flags`'s flags."""
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    return seeds, tuple(s.strip() for s in args.suites.split(",") if s.strip())


def covey_eval(out: str, seed: int, vehicles: str, suites, controllers, **fields) -> dict:
    """One `covey eval` run, the C core's controllers available (firmware/ceval.py), without
    figures or a progress bar: its results.json as a dict (summary and runs). `fields`: more
    EvalConfig fields."""
    from firmware import ceval
    from policy.eval import EvalConfig

    cfg = EvalConfig(
        out=out,
        seed=seed,
        figures=False,
        progress=False,
        controllers=tuple(controllers),
        suites=tuple(suites),
        vehicles=vehicles,
        **fields,
    )
    return ceval.main(cfg)


def children() -> ChildGroup:
    """Python children of a benchmark (`kids.start("-m", "bench.mesh", ...)`), each in its own
    process group, stdout captured (`child.wait_for("READY")`), stderr discarded; all stopped
    (SIGTERM, SIGKILL after 3 s) when the `with` block ends."""
    return ChildGroup(
        prefix=[sys.executable], cwd=REPO, env=python_env(REPO), stderr="discard", grace_s=3.0
    )


def start_routers(
    kids: ChildGroup, count: int, *, chain: bool = False, tries: int = 3
) -> list[tuple[Child, int]]:
    """Start `count` `covey router`s on loopback, one after the other, each connected to every
    one before it (a full mesh) or, with `chain`, to the one before it; returns (child, port)
    of each, R1 first, each READY. A port is picked just before its router starts, and a router
    that exits before READY (its port taken meanwhile, by another process's outgoing
    connection) is started again on a new one, up to `tries` times."""
    from comms.session import free_tcp_port

    started: list[tuple[Child, int]] = []
    for _ in range(count):
        peers = [p for _, p in started][-1:] if chain else [p for _, p in started]
        for attempt in range(1, tries + 1):
            port = free_tcp_port()
            argv = ["-m", "covey_cli", "router", "--listen", f"tcp/127.0.0.1:{port}"]
            if peers:
                argv += ["--connect", ",".join(f"tcp/127.0.0.1:{p}" for p in peers)]
            child = kids.start(*argv)
            try:
                child.wait_for("READY", 60)
            except ChildExited:
                if attempt == tries:
                    raise
                continue
            started.append((child, port))
            break
    return started


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process `pid` and its threads so far (from /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_in_tree(tree: Path, script: Path, argv: list[str]) -> Any:
    """Run the bench file `script` on another checkout's packages (`tree`, e.g. main before a
    change) and return what it printed last, as JSON: the file is copied out of bench/ (which
    would shadow the packages) and run with `tree` on PYTHONPATH and as the working directory.
    """
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    with tempfile.TemporaryDirectory() as d:
        copy = Path(d) / f"{script.stem}_bench.py"
        shutil.copy(script, copy)
        out = subprocess.run(
            [sys.executable, str(copy), *argv],
            env=env,
            cwd=tree,
            check=True,
            capture_output=True,
            text=True,
        )
    return json.loads(out.stdout.strip().splitlines()[-1])
