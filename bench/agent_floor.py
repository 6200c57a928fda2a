"""The floor under one agent's CPU per tick: its tick hot and cold, the wait between ticks, and
the Ed25519 work per state (a profiling aid beside bench/agent_profile.py, not a `covey bench`
section).

    python -m bench.agent_floor [--ticks 300] [--neighbours 20] [--numpy]
    python -m bench.agent_floor --compare-tree /tmp/before   # that checkout and this, alternating

In-process, on an injected clock: one `Agent` (sim backend, open mode, a router of its own and
nobody else) takes off and flies a long goto, its guidance in the C core as `covey agent` flies
it (`--numpy`: the numpy reference); `--neighbours` vehicles on a ring 6-14 m around it fly
along with it (bench/agent_cpu.py's ring), put straight into its neighbour table before each
tick (the receive path is bench/agent_receive.py's). Its tick's CPU (thread time) is measured
back to back ("hot": caches warm) and with a real 100 ms sleep before each tick, as a 10 Hz
agent runs ("cold": whatever else the machine ran since has evicted its code and data). The
cost of the sleep itself (`threading.Event.wait(0.1)`, what kit/ticks.py waits on) and of one
Ed25519 signature and verification (`cryptography`, a state's size) are measured alone.
Medians of `--repeats` runs, printed and written to bench/results/agent_floor.json; with
`--compare-tree`, each repeat runs that checkout's agent first, then this one's.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import threading
import time
from pathlib import Path

from bench import common


def _agent_ticks(ticks: int, sleep_s: float, neighbours: int = 0, c_core: bool = True) -> float:
    """CPU ms per tick of a flying agent with `neighbours` around it, each tick after a
    `sleep_s` sleep."""
    from agent.backends.sim import SimBackend, SimConfig
    from agent.failsafe import FailsafeConfig
    from agent.guidance import GuidanceConfig
    from agent.hosts import Agent
    from agent.shell_config import AgentConfig
    from comms.mesh import Mesh
    from comms.schema import AckResult, Command, Mode, VehicleState
    from comms.session import embedded_router, free_tcp_port

    t = [0.0]
    seq = [0]

    def ring() -> None:
        """The neighbours around the agent, at its altitude and velocity, as heard now."""
        obs = ag.vehicles.read()
        (n, e, d), vel = obs.pos_m[0].tolist(), tuple(obs.vel_m_s[0].tolist())
        seq[0] += 1
        for k in range(neighbours):
            r_m, th = 6.0 + 8.0 * k / neighbours, 2 * math.pi * k / neighbours + 0.3
            pos = (n + r_m * math.cos(th), e + r_m * math.sin(th), d)
            stamp_ns = int(t[0] * 1e9)
            ag.table.update(
                VehicleState(100 + k, seq[0], stamp_ns, pos, vel, 0.0, Mode.GOTO, True), t[0]
            )

    with Mesh(embedded_router(free_tcp_port(), fleet="floor")) as mesh:
        cfg = AgentConfig(
            vehicle_id=1,
            failsafe=FailsafeConfig(require_gcs=False),
            guidance=GuidanceConfig(c_core=c_core),
        )
        with Agent(cfg, SimBackend(SimConfig(), now_s=0.0), mesh, clock_s=lambda: t[0]) as ag:
            ag.handle_command(Command.takeoff(10.0, nonce=1, stamp_ns=0))
            for _ in range(600):
                t[0] += 0.1
                ag.tick(t[0])
                if ag.mode is Mode.HOLDING:
                    break
            # far enough to fly the whole run (1 m/s), within the agent's 500 m geofence
            ack = ag.handle_command(Command.goto_local(400.0, 0.0, -10.0, nonce=2, stamp_ns=0))
            if ack.result is not AckResult.ACCEPTED:
                raise RuntimeError(f"goto refused: {ack.reason}")
            for _ in range(20):  # the neighbours heard, the first decisions made
                t[0] += 0.1
                ring()
                ag.tick(t[0])
            cpu_s = 0.0
            for _ in range(ticks):
                if sleep_s:
                    time.sleep(sleep_s)
                t[0] += 0.1
                ring()
                c0 = time.thread_time()
                ag.tick(t[0])
                cpu_s += time.thread_time() - c0
            if ag.mode is not Mode.GOTO:
                raise RuntimeError(f"the agent left its goto ({ag.mode.name}): not a flying tick")
    return cpu_s * 1e3 / ticks


def _wait_us(n: int = 20) -> float:
    ev = threading.Event()
    c0 = time.process_time()
    for _ in range(n):
        ev.wait(0.1)
    return (time.process_time() - c0) * 1e6 / n


def _ed25519_us(n: int = 2000) -> tuple[float, float]:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    key = Ed25519PrivateKey.generate()
    pub, msg = key.public_key(), bytes(120)
    sig = key.sign(msg)
    c0 = time.process_time()
    for _ in range(n):
        key.sign(msg)
    c1 = time.process_time()
    for _ in range(n):
        pub.verify(sig, msg)
    c2 = time.process_time()
    return (c1 - c0) * 1e6 / n, (c2 - c1) * 1e6 / n


def measure(ticks: int, neighbours: int, c_core: bool) -> dict:
    """One run of every measurement (ms and us)."""
    sign, verify = _ed25519_us()
    return {
        "tick_hot_ms": _agent_ticks(ticks, 0.0, neighbours, c_core),
        "tick_cold_ms": _agent_ticks(max(20, ticks // 10), 0.1, neighbours, c_core),
        "wait_100ms_us": _wait_us(),
        "ed25519_sign_us": sign,
        "ed25519_verify_us": verify,
    }


def medians(runs: list[dict]) -> dict:
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    med["cold_over_hot"] = med["tick_cold_ms"] / med["tick_hot_ms"]
    return med


def main(
    ticks: int = 300,
    repeats: int = 3,
    neighbours: int = 20,
    c_core: bool = True,
    compare_tree: Path | None = None,
) -> dict:
    argv = ["--ticks", str(ticks), "--neighbours", str(neighbours), "--json"]
    argv += [] if c_core else ["--numpy"]
    runs, before = [], []
    for _ in range(repeats):
        if compare_tree is not None:
            before.append(common.run_in_tree(compare_tree, Path(__file__), argv))
        runs.append(measure(ticks, neighbours, c_core))
    result = {
        **medians(runs),
        "runs": runs,
        "neighbours": neighbours,
        "guidance": "C core" if c_core else "numpy",
        "repeats": repeats,
        "machine": common.machine(),
    }
    what = f"flying tick, {neighbours} neighbours, {result['guidance']}"
    if before:
        b = medians(before)
        result["before"] = {"tree": str(compare_tree), **b, "runs": before}
        for k in ("tick_hot_ms", "tick_cold_ms"):
            result[f"{k}_over_before"] = result[k] / b[k]
        common.say(
            f"{what}, {compare_tree}: hot {b['tick_hot_ms']:.3f} ms, cold "
            f"{b['tick_cold_ms']:.3f} ms (medians of {repeats}: "
            + ", ".join(f"{r['tick_cold_ms']:.3f}" for r in before)
            + ")"
        )
    common.say(
        f"{what}: hot {result['tick_hot_ms']:.3f} ms, after a 100 ms sleep "
        f"{result['tick_cold_ms']:.3f} ms ({result['cold_over_hot']:.2f}x; cold runs "
        + ", ".join(f"{r['tick_cold_ms']:.3f}" for r in runs)
        + f"); Event.wait(0.1) {result['wait_100ms_us']:.0f} us; Ed25519 sign "
        f"{result['ed25519_sign_us']:.0f} us, verify {result['ed25519_verify_us']:.0f} us"
    )
    if before:
        common.say(
            f"this tree / {compare_tree}: hot {result['tick_hot_ms_over_before']:.2f}, cold "
            f"{result['tick_cold_ms_over_before']:.2f}"
        )
    common.write_json("agent_floor", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=300, help="hot ticks per run (cold: a tenth)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--neighbours", type=int, default=20, help="vehicles flying around it")
    ap.add_argument("--numpy", action="store_true", help="guidance in numpy, not the C core")
    ap.add_argument(
        "--compare-tree",
        type=Path,
        default=None,
        metavar="PATH",
        help="another checkout (e.g. main before a change), measured first in each repeat",
    )
    ap.add_argument("--json", action="store_true", help="one run of this tree, as JSON only")
    a = ap.parse_args()
    if a.ticks < 20 or a.repeats < 1 or a.neighbours < 0:
        ap.error("--ticks must be at least 20, --repeats at least 1, --neighbours at least 0")
    if a.compare_tree is not None and not (a.compare_tree / "agent" / "shell.py").exists():
        ap.error(f"--compare-tree {a.compare_tree}: no covey checkout there")
    if a.json:
        print(json.dumps(measure(a.ticks, a.neighbours, not a.numpy)))
    else:
        main(a.ticks, a.repeats, a.neighbours, not a.numpy, a.compare_tree)
