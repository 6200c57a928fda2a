"""CPU of landed, idle `covey agent` processes: one, and 40 of them as `covey demo` starts them.

    python -m bench.idle_agents [--quick]                  # writes idle_agents.json
    python -m bench.idle_agents --compare-tree ../main --repeats 3   # before / after

Issue 15's target: 40 separate agent processes, landed and idle, use at most 25 % of a 2-core
machine. `covey demo --vehicles N` (keyed: every state signed, and verified by its receivers; a
6 m grid, so all N are within reach of each other; no command is sent) starts N agents. Once all
N are present on the mesh (liveliness) and `settle_s` has passed, the CPU time of the agent
processes (user + system, all threads, from /proc) over `window_s` is summed and given as a
share of 2 cores; the demo process itself (router and station) and the whole machine are
reported beside it, so a busy machine shows. This process joins the mesh to see who is present
and to count the states it receives.

With `--compare-tree PATH` (another checkout, such as main before a change; repeatable), each
repeat measures those trees and then this one, N = 1 then N = 40 (alternating, so that other load
on the machine falls on all of them), and the JSON keeps every run and the medians.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench import common
from kit.procs import Child

TARGET_SHARE_OF_2_CORES = 0.25
"""Issue 15: 40 idle agents use at most a quarter of this 2-core machine."""


@dataclass(frozen=True)
class IdleBenchConfig:
    """What one measurement starts and how long it watches."""

    vehicles: int = 40
    """Agents `covey demo` starts (one process each)."""
    tree: Path = common.REPO
    """The checkout whose `covey demo` runs (its code is the one imported: cwd and PYTHONPATH)."""
    settle_s: float = 10.0
    """Wait this long after the last vehicle appears (start-up work, first rosters) before the window."""
    window_s: float = 10.0
    """CPU is summed over this window."""
    start_timeout_s: float = 300.0
    """All vehicles must be present this soon (40 interpreters start slowly on 2 cores)."""


def machine_busy_s() -> float:
    """Busy CPU seconds of the whole machine so far (all cores, from /proc/stat)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """CPU seconds so far of process `pid`, all its threads, to the nanosecond (the scheduler's
    run time in /proc/<pid>/task/*/schedstat; /proc/<pid>/stat counts 10 ms ticks, too coarse
    for one idle agent over 10 s)."""
    total_ns = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            total_ns += int(Path(f"/proc/{pid}/task/{task}/schedstat").read_text().split()[0])
        except (OSError, IndexError, ValueError):
            pass  # a thread that ended meanwhile
    return total_ns / 1e9


def all_cpu_s() -> dict[int, float]:
    """CPU seconds so far of every process on the machine."""
    out = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                out[int(name)] = common.cpu_seconds(int(name))
            except (OSError, IndexError, ValueError):
                pass
    return out


def busiest(before: dict[int, float], after: dict[int, float], skip: set[int], wall_s: float):
    """The five other processes that used the most CPU in between: (share of 2 cores, command)."""
    used = sorted(
        ((after[p] - before[p], p) for p in after.keys() & before.keys() if p not in skip),
        reverse=True,
    )[:5]
    rows = []
    for cpu_s, pid in used:
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            cmd = "?"
        rows.append([round(cpu_s / wall_s / 2, 3), cmd.strip()[:100]])
    return rows


def _imports_from(pid: int) -> str:
    """Where process `pid` imports covey from: its PYTHONPATH (else its working folder)."""
    try:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        path = next((e[11:].decode() for e in env if e.startswith(b"PYTHONPATH=")), "")
        return path or os.readlink(f"/proc/{pid}/cwd")
    except OSError:
        return "?"


def measure(cfg: IdleBenchConfig) -> dict:
    """Start `covey demo --vehicles N` from `cfg.tree`, wait for every vehicle, sum CPU."""
    from comms.mesh import Mesh
    from comms.session import MeshConfig

    env = dict(os.environ, PYTHONPATH=str(cfg.tree), PYTHONUNBUFFERED="1")
    argv = [sys.executable, "-m", "covey_cli", "demo", "--vehicles", str(cfg.vehicles)]
    with Child(
        [*argv, "--port", "0"],
        cwd=cfg.tree,
        env=env,
        stop_signal=signal.SIGINT,  # the demo stops its agents in order
        grace_s=20.0,
    ) as demo:
        endpoint = demo.wait_for("covey demo: mesh ", 120).split()[3]
        pids = [
            int(line.split()[5])
            for line in demo.lines()
            if line.startswith("covey demo: vehicle ") and " pid " in line
        ]
        if len(pids) != cfg.vehicles:
            raise RuntimeError(f"the demo started {len(pids)} agents, not {cfg.vehicles}")
        mesh_cfg = MeshConfig(fleet="covey", mode="peer", connect=(endpoint,), listen=())
        with Mesh(mesh_cfg) as mesh:
            pres = mesh.presence()
            t0 = time.monotonic()
            if not pres.wait_for(lambda v, _g: len(v) >= cfg.vehicles, cfg.start_timeout_s):
                raise RuntimeError(
                    f"only {len(pres.vehicles)} of {cfg.vehicles} vehicles came up in "
                    f"{cfg.start_timeout_s:g} s"
                )
            up_s = time.monotonic() - t0
            counts: dict[int, int] = {}
            lock = threading.Lock()

            def on_state(s, _t: int) -> None:
                with lock:
                    counts[s.vehicle_id] = counts.get(s.vehicle_id, 0) + 1

            mesh.subscribe_states(on_state)
            time.sleep(cfg.settle_s)
            everyone = [demo.pid, *pids]
            with lock:
                counts.clear()
            # wall time from the middle of one sweep of reads to the middle of the next: 41
            # processes' reads take a while on a saturated machine
            all0, m0, t0 = all_cpu_s(), machine_busy_s(), time.perf_counter()
            c0 = {p: cpu_s(p) for p in everyone}
            w0 = (t0 + time.perf_counter()) / 2
            time.sleep(cfg.window_s)
            t1 = time.perf_counter()
            c1 = {p: cpu_s(p) for p in everyone}
            wall_s = (t1 + time.perf_counter()) / 2 - w0
            m1, all1 = machine_busy_s(), all_cpu_s()
            with lock:
                received = dict(counts)
        tree_seen = sorted({_imports_from(p) for p in pids})
    agents_s = sum(c1[p] - c0[p] for p in pids)
    demo_s = c1[demo.pid] - c0[demo.pid]
    rates = np.array([received.get(v, 0) for v in range(1, cfg.vehicles + 1)]) / wall_s
    return {
        "vehicles": cfg.vehicles,
        "tree": str(cfg.tree),
        "agents_import_from": tree_seen,
        "start_s": up_s,
        "window_s": wall_s,
        "agents_share_of_2_cores": agents_s / wall_s / 2,
        "agent_cpu_ms_per_s": 1e3 * agents_s / wall_s / cfg.vehicles,
        "demo_process_share_of_2_cores": demo_s / wall_s / 2,
        "machine_busy_share_of_all_cores": (m1 - m0) / wall_s / (os.cpu_count() or 1),
        "others_share_of_2_cores": max(0.0, (m1 - m0) - agents_s - demo_s) / wall_s / 2,
        "states_hz_per_vehicle_p50": float(np.median(rates)),
        "others_busiest": busiest(all0, all1, {*everyone, os.getpid()}, wall_s),
    }


def _row(r: dict) -> str:
    return (
        f"{r['vehicles']:>3} agents from {r['tree']}: {100 * r['agents_share_of_2_cores']:.1f} % "
        f"of 2 cores ({r['agent_cpu_ms_per_s']:.1f} ms/s each), demo process "
        f"{100 * r['demo_process_share_of_2_cores']:.1f} %, others on the machine "
        f"{100 * r['others_share_of_2_cores']:.1f} %; states {r['states_hz_per_vehicle_p50']:.1f} Hz each"
    )


def run(
    vehicles: tuple[int, ...],
    trees: tuple[Path, ...],
    repeats: int,
    settle_s: float,
    window_s: float,
) -> dict:
    """Every (repeat, tree, vehicles) measurement, alternating trees, and medians per pair."""
    runs = []
    for rep in range(repeats):
        for tree in trees:
            for n in vehicles:
                r = measure(IdleBenchConfig(n, tree, settle_s, window_s))
                r["repeat"] = rep
                common.say(_row(r))
                runs.append(r)
    medians = []
    for tree in trees:
        for n in vehicles:
            mine = [r for r in runs if r["tree"] == str(tree) and r["vehicles"] == n]
            medians.append(
                {
                    "tree": str(tree),
                    "vehicles": n,
                    "runs": len(mine),
                    **{
                        k: float(np.median([r[k] for r in mine]))
                        for k in (
                            "agents_share_of_2_cores",
                            "agent_cpu_ms_per_s",
                            "demo_process_share_of_2_cores",
                            "others_share_of_2_cores",
                            "states_hz_per_vehicle_p50",
                        )
                    },
                }
            )
    return {"runs": runs, "medians": medians}


def main(
    quick: bool = False,
    compare_trees: tuple[Path, ...] = (),
    repeats: int = 1,
    vehicles: tuple[int, ...] | None = None,
) -> dict:
    vehicles = vehicles or ((1, 10) if quick else (1, 40))
    trees = (*(t.resolve() for t in compare_trees), common.REPO)
    result = run(vehicles, trees, repeats, 3.0 if quick else 10.0, 4.0 if quick else 10.0)
    mine = [m for m in result["medians"] if m["tree"] == str(common.REPO)]
    most = max(mine, key=lambda m: m["vehicles"])
    result.update(
        quick=quick,
        target_share_of_2_cores=TARGET_SHARE_OF_2_CORES,
        meets_target=bool(
            most["vehicles"] >= 40 and most["agents_share_of_2_cores"] <= TARGET_SHARE_OF_2_CORES
        ),
    )
    for m in result["medians"]:
        common.say("median: " + _row({**m, "tree": m["tree"]}))
    common.write_json("idle_agents", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 and 10 agents, short windows")
    ap.add_argument(
        "--compare-tree",
        type=Path,
        action="append",
        default=[],
        help="another checkout to measure too, alternating with this one (e.g. main); repeatable",
    )
    ap.add_argument("--repeats", type=int, default=1, help="measurements of each (default 1)")
    ap.add_argument(
        "--vehicles",
        default=None,
        help="comma-separated agent counts (default 1,40; --quick 1,10)",
    )
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {a.repeats}")
    for tree in a.compare_tree:
        if not (tree / "covey_cli.py").is_file():
            ap.error(f"--compare-tree {tree}: no covey checkout there (no covey_cli.py)")
    counts = None
    if a.vehicles:
        try:
            counts = tuple(int(v) for v in a.vehicles.split(","))
        except ValueError:
            ap.error(f"--vehicles {a.vehicles!r}: comma-separated whole numbers, e.g. 1,40")
        if not all(1 <= v <= 200 for v in counts):
            ap.error(f"--vehicles {a.vehicles!r}: each within 1..200 (covey demo's limit)")
    main(a.quick, tuple(a.compare_tree), a.repeats, counts)
