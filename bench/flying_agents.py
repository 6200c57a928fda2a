"""CPU of N real `covey agent` processes from `covey demo`, idle, hovering and flying gotos.

    python -m bench.flying_agents [--quick]                     # writes flying_agents.json/.png
    python -m bench.flying_agents --compare-tree /work/main     # that checkout, then this one

Issue 37's targets: 40 real agents hovering and flying on this 2-core machine use at most 25 %
of it, and one flying agent with ~20 neighbours uses at most 1 ms of CPU per 10 Hz tick
(bench/agent_profile.py splits that one). `covey demo --vehicles N --spacing-m 8` (keyed: every
state signed by its vehicle and verified by its receivers) starts N agents; this process joins
the mesh as the demo's command-line station and measures three phases, each over `window_s`:

- idle: landed, no command sent;
- hovering: after `takeoff 6` to all, once every vehicle holds at altitude;
- flying: each vehicle sent a goto to its own random point 30-60 m away within 80 m of the
  origin, at its altitude (seeded), measured while most are still on their way.

CPU time (user + system, all threads, /proc schedstat) is summed per process role: the agents,
the demo process (router and ground station), this process; the rest of the machine is given
beside them, with the load average, since other work on the machine slows everything. Tick
jitter: a state goes out on a guidance tick, so the gap between two states of a vehicle is a
whole number of tick periods plus the jitter (|gap - round(gap / period) period|), whatever
the state rate. With `--compare-tree`, each tree runs the same N and phases, alternating, so
that the machine's other load falls on both.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench import common
from bench.idle_agents import cpu_s, machine_busy_s
from kit.procs import Child

TARGET_SHARE_OF_2_CORES = 0.25
"""Issue 37: 40 agents hovering and flying use at most a quarter of this 2-core machine."""
TICK_HZ = 10.0
PHASES = ("idle", "hovering", "flying")


@dataclass(frozen=True)
class FlyingBenchConfig:
    """One measurement: which checkout, how many agents, how long each window."""

    vehicles: int = 40
    """Agents `covey demo` starts (one process each)."""
    tree: Path = common.REPO
    """The checkout whose `covey demo` runs (its code is imported: cwd and PYTHONPATH)."""
    window_s: float = 10.0
    """CPU is summed over this window in each phase."""
    settle_s: float = 5.0
    """Wait this long after a phase is reached before its window."""
    spacing_m: float = 8.0
    """Grid spacing of the start positions (issue 37's demo: 8 m)."""
    takeoff_alt_m: float = 6.0
    seed: int = 37
    start_timeout_s: float = 300.0
    """All vehicles present this soon (40 interpreters start slowly on 2 cores)."""
    profile_out: str | None = None
    """py-spy one agent (the middle of the grid) over the flying window, the profile written
    here (a profiling aid: py-spy is no dependency, and it slows the agent it samples)."""


class Watch:
    """Every vehicle's latest state and its state stamps, as this process receives them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.latest: dict[int, object] = {}
        self.stamps: dict[int, list[int]] = {}

    def on_state(self, s, _recv_ns: int) -> None:
        with self.lock:
            self.latest[s.vehicle_id] = s
            self.stamps.setdefault(s.vehicle_id, []).append(s.stamp_ns)

    def clear_stamps(self) -> None:
        with self.lock:
            self.stamps = {}

    def wait(self, pred, n: int, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                ok = sum(1 for s in self.latest.values() if pred(s))
            if ok >= n:
                return
            time.sleep(0.2)
        raise RuntimeError(f"only {ok} of {n} vehicles got to {what} in {timeout_s:g} s")

    def jitter_ms(self) -> np.ndarray:
        """|gap - nearest whole number of tick periods| of every gap between two states."""
        period_ns = 1e9 / TICK_HZ
        with self.lock:
            gaps = [np.diff(np.sort(np.array(v, dtype=float))) for v in self.stamps.values()]
        g = np.concatenate(gaps) if gaps else np.zeros(0)
        g = g[g > 0]
        return np.abs(g - np.round(g / period_ns) * period_ns) / 1e6

    def state_hz(self, window_s: float) -> float:
        with self.lock:
            counts = [len(v) for v in self.stamps.values()]
        return float(np.median(counts)) / window_s if counts else 0.0


def window(pids: list[int], demo_pid: int, watch: Watch, window_s: float, n: int) -> dict:
    """CPU by role over `window_s`, shares of 2 cores, and the tick jitter."""
    me = os.getpid()
    everyone = [*pids, demo_pid, me]
    watch.clear_stamps()
    c0, m0, t0 = {p: cpu_s(p) for p in everyone}, machine_busy_s(), time.perf_counter()
    time.sleep(window_s)
    c1, m1, t1 = {p: cpu_s(p) for p in everyone}, machine_busy_s(), time.perf_counter()
    wall_s = t1 - t0
    per_agent = np.array([c1[p] - c0[p] for p in pids]) / wall_s
    agents_s = float(per_agent.sum()) * wall_s
    demo_s, me_s = c1[demo_pid] - c0[demo_pid], c1[me] - c0[me]
    jit = watch.jitter_ms()
    return {
        "window_s": wall_s,
        "agents_share_of_2_cores": agents_s / wall_s / 2,
        "agent_cpu_ms_per_s_p50": 1e3 * float(np.median(per_agent)),
        "agent_cpu_ms_per_s_max": 1e3 * float(per_agent.max()),
        "agent_cpu_ms_per_tick_mean": 1e3 * agents_s / wall_s / n / TICK_HZ,
        "demo_process_share_of_2_cores": demo_s / wall_s / 2,
        "bench_process_share_of_2_cores": me_s / wall_s / 2,
        "others_share_of_2_cores": max(0.0, (m1 - m0) - agents_s - demo_s - me_s) / wall_s / 2,
        "state_hz_per_vehicle_p50": watch.state_hz(wall_s),
        "tick_jitter_ms_p50": common.pct(jit, 50),
        "tick_jitter_ms_p99": common.pct(jit, 99),
        "loadavg_1_5_15": [round(x, 2) for x in os.getloadavg()],
    }


def random_gotos(
    rng: np.random.Generator, starts: dict[int, tuple[float, float]], alt_m: float
) -> dict[int, tuple[float, float, float]]:
    """For each vehicle a point 30-60 m from where it is, within 80 m of the origin."""
    out = {}
    for vid, (n, e) in starts.items():
        while True:
            r_m, th = rng.uniform(30.0, 60.0), rng.uniform(0.0, 2 * np.pi)
            p = (n + r_m * np.cos(th), e + r_m * np.sin(th))
            if np.hypot(*p) <= 80.0:
                break
        out[vid] = (float(p[0]), float(p[1]), -alt_m)
    return out


def measure(cfg: FlyingBenchConfig) -> dict:
    """Start `covey demo` from `cfg.tree`; idle, take off, hover, fly gotos; CPU per phase."""
    from comms.commands import OutcomeStatus, new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command, Mode
    from comms.session import MeshConfig
    from trust.auth import load_auth

    env = dict(os.environ, PYTHONPATH=str(cfg.tree), PYTHONUNBUFFERED="1")
    argv = [sys.executable, "-m", "covey_cli", "demo", "--vehicles", str(cfg.vehicles)]
    argv += ["--port", "0", "--mesh-port", "0", "--spacing-m", f"{cfg.spacing_m:g}"]
    argv += ["--geofence-radius-m", "100"]
    out: dict = {"vehicles": cfg.vehicles, "tree": str(cfg.tree)}
    with Child(argv, cwd=cfg.tree, env=env, stop_signal=signal.SIGINT, grace_s=20.0) as demo:
        line = demo.wait_for("covey demo: mesh ", 120)
        endpoint = line.split()[3]
        key_file = line.split("--key-file ", 1)[1].rstrip(")").split()[0]
        pids = [
            int(ln.split()[5])
            for ln in demo.lines()
            if ln.startswith("covey demo: vehicle ") and " pid " in ln
        ]
        starts = {
            int(ln.split()[3]): (float(ln.split()[8]), float(ln.split()[10]))
            for ln in demo.lines()
            if ln.startswith("covey demo: vehicle ") and " pid " in ln
        }
        if len(pids) != cfg.vehicles:
            raise RuntimeError(f"the demo started {len(pids)} agents, not {cfg.vehicles}")
        mesh_cfg = MeshConfig(fleet="covey", mode="peer", connect=(endpoint,), listen=())
        # Two sessions: a keyed one signs the commands; an open one watches the states, unchecked,
        # so that a loaded machine's late states still count (a keyed gate refuses them as stale).
        with (
            Mesh(mesh_cfg, auth=load_auth(key_file, fleet="covey")) as mesh,
            Mesh(mesh_cfg) as watcher,
        ):
            watch = Watch()
            watcher.subscribe_states(watch.on_state)
            t0 = time.monotonic()
            watch.wait(lambda s: True, cfg.vehicles, cfg.start_timeout_s, "their first state")
            out["start_s"] = time.monotonic() - t0
            time.sleep(cfg.settle_s)
            out["idle"] = window(pids, demo.pid, watch, cfg.window_s, cfg.vehicles)
            ids = tuple(range(1, cfg.vehicles + 1))

            def command(make, vids: tuple[int, ...], tries: int = 3) -> set[int]:
                """Send `make(targets)` until every one of `vids` accepted it (a loaded machine
                can miss an ack); the ids that did."""
                done: set[int] = set()
                for _ in range(tries):
                    left = tuple(v for v in vids if v not in done)
                    if not left:
                        break
                    res = mesh.send_command(make(left), expect=left, timeout_s=20)
                    done |= {
                        v for v, o in res.outcomes.items() if o.status is OutcomeStatus.ACCEPTED
                    }
                return done

            def fresh(**kw) -> dict:
                return {**kw, "nonce": new_nonce(), "stamp_ns": time.time_ns()}

            up = command(lambda t: Command.takeoff(cfg.takeoff_alt_m, **fresh(targets=t)), ids)
            if len(up) < cfg.vehicles:
                raise RuntimeError(f"takeoff accepted by {len(up)} of {cfg.vehicles}")
            # all but one in 20 (a loaded machine can leave one still climbing or stepping aside)
            most = cfg.vehicles - cfg.vehicles // 20
            watch.wait(lambda s: s.mode is Mode.HOLDING, most, 240, "hover")
            time.sleep(cfg.settle_s)
            out["hovering"] = window(pids, demo.pid, watch, cfg.window_s, cfg.vehicles)
            with watch.lock:
                out["hovering"]["holding"] = sum(
                    s.mode is Mode.HOLDING for s in watch.latest.values()
                )
            gotos = random_gotos(np.random.default_rng(cfg.seed), starts, cfg.takeoff_alt_m)
            with ThreadPoolExecutor(8) as pool:  # one command per vehicle, 8 in flight
                sent = pool.map(
                    lambda item: command(
                        lambda t, p=item[1]: Command.goto_local(*p, **fresh(targets=t)),
                        (item[0],),
                    ),
                    gotos.items(),
                )
                flying = set().union(*sent)
            time.sleep(1.0)
            pid_of = {
                int(ln.split()[3]): int(ln.split()[5])
                for ln in demo.lines()
                if ln.startswith("covey demo: vehicle ") and " pid " in ln
            }
            spied = _spy_while(cfg, pid_of, starts)
            out["flying"] = window(pids, demo.pid, watch, cfg.window_s, cfg.vehicles)
            if spied is not None:
                spied.join()
            out["flying"]["gotos_accepted"] = len(flying)
            with watch.lock:
                out["flying"]["in_goto_at_end"] = sum(
                    s.mode is Mode.GOTO for s in watch.latest.values()
                )
    return out


def _spy_while(
    cfg: FlyingBenchConfig, pid_of: dict[int, int], starts: dict
) -> threading.Thread | None:
    """With cfg.profile_out: py-spy the agent nearest the grid's middle over the next window."""
    if cfg.profile_out is None:
        return None
    from bench.agent_profile import profile_lines, py_spy

    ids = sorted(starts)
    mid = np.mean([starts[v] for v in ids], axis=0)
    vid = ids[int(np.argmin([np.hypot(*(np.array(starts[v]) - mid)) for v in ids]))]
    pid, folded, out = pid_of[vid], cfg.profile_out + ".folded", cfg.profile_out

    def run() -> None:
        by_thread = py_spy(pid, cfg.window_s, folded)
        head = f"agent {vid} of {cfg.vehicles} flying gotos (pid {pid})"
        lines = profile_lines(head, folded, by_thread, 200)
        Path(out).write_text("\n".join(lines) + "\n")
        common.say("\n".join(lines[:12]))

    t = threading.Thread(target=run, name="py-spy")
    t.start()
    return t


def _row(r: dict, phase: str) -> str:
    p = r[phase]
    return (
        f"{r['vehicles']:>3} agents {phase:>8} ({Path(r['tree']).name}): "
        f"{100 * p['agents_share_of_2_cores']:.1f} % of 2 cores, "
        f"{p['agent_cpu_ms_per_tick_mean']:.2f} ms/tick each, demo "
        f"{100 * p['demo_process_share_of_2_cores']:.1f} %, others "
        f"{100 * p['others_share_of_2_cores']:.1f} %, states {p['state_hz_per_vehicle_p50']:.1f} Hz, "
        f"jitter p99 {p['tick_jitter_ms_p99']:.1f} ms, load {p['loadavg_1_5_15'][0]}"
    )


def plot(runs: list[dict]) -> None:
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    trees = sorted({r["tree"] for r in runs})
    styles = {"idle": ":s", "hovering": "--^", "flying": "-o"}
    for ti, tree in enumerate(trees):
        mine = sorted((r for r in runs if r["tree"] == tree), key=lambda r: r["vehicles"])
        label = "this tree" if tree == str(common.REPO) else Path(tree).name
        for phase in PHASES:
            ax.plot(
                [r["vehicles"] for r in mine],
                [r[phase]["agent_cpu_ms_per_tick_mean"] for r in mine],
                styles[phase],
                color=f"C{ti}",
                label=f"{label}: {phase}",
            )
    ax.axhline(1.0, color="k", lw=0.8)
    ax.text(0.01, 1.03, "target: 1 ms per tick", fontsize=8, transform=ax.get_yaxis_transform())
    ax.set_xlabel("agents (covey demo, keyed, 8 m grid)")
    ax.set_ylabel("CPU ms per agent per 10 Hz tick")
    ax.set_title("Real agent processes on 2 cores")
    ax.legend(fontsize=7)
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.12, top=0.92)
    common.save_figure(fig, "flying_agents")


def main(
    quick: bool = False,
    compare_trees: tuple[Path, ...] = (),
    vehicles: tuple[int, ...] | None = None,
    profile_out: str | None = None,
) -> dict:
    vehicles = vehicles or ((5,) if quick else (10, 20, 40))
    trees = (*(t.resolve() for t in compare_trees), common.REPO)
    window_s, settle_s = (4.0, 2.0) if quick else (10.0, 5.0)
    runs, failed = [], []
    for n in vehicles:
        for tree in trees:
            try:
                r = measure(FlyingBenchConfig(n, tree, window_s, settle_s, profile_out=profile_out))
            except RuntimeError as exc:  # a machine too loaded to take off all N: say so, go on
                common.say(f"{n} agents from {tree}: {exc}")
                failed.append({"vehicles": n, "tree": str(tree), "error": str(exc)})
                continue
            for phase in PHASES:
                common.say(_row(r, phase))
            runs.append(r)
    if not runs:
        raise RuntimeError(f"no measurement completed: {failed}")
    plot(runs)
    mine = [r for r in runs if r["tree"] == str(common.REPO)]
    most = max(mine, key=lambda r: r["vehicles"]) if mine else None
    result = {
        "quick": quick,
        "tick_hz": TICK_HZ,
        "target_share_of_2_cores": TARGET_SHARE_OF_2_CORES,
        "meets_target": bool(
            most is not None
            and most["vehicles"] >= 40
            and all(
                most[p]["agents_share_of_2_cores"] <= TARGET_SHARE_OF_2_CORES
                for p in ("hovering", "flying")
            )
        ),
        "runs": runs,
        "failed": failed,
    }
    common.write_json("flying_agents", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 agents, short windows")
    ap.add_argument(
        "--compare-tree",
        type=Path,
        action="append",
        default=[],
        help="another checkout to measure too, alternating with this one (e.g. main); repeatable",
    )
    ap.add_argument(
        "--vehicles", default=None, help="comma-separated agent counts (default 10,20,40)"
    )
    ap.add_argument(
        "--profile-out",
        default=None,
        metavar="PATH",
        help="py-spy one agent over the flying window and write its profile here (needs "
        "py-spy; the profiled agent runs slower)",
    )
    a = ap.parse_args()
    for tree in a.compare_tree:
        if not (tree / "covey_cli.py").is_file():
            ap.error(f"--compare-tree {tree}: no covey checkout there (no covey_cli.py)")
    counts = None
    if a.vehicles:
        try:
            counts = tuple(int(v) for v in a.vehicles.split(","))
        except ValueError:
            ap.error(f"--vehicles {a.vehicles!r}: comma-separated whole numbers, e.g. 10,20,40")
        if not all(1 <= v <= 200 for v in counts):
            ap.error(f"--vehicles {a.vehicles!r}: each within 1..200 (covey demo's limit)")
    main(a.quick, tuple(a.compare_tree), counts, a.profile_out)
