"""The floor under one agent's CPU per tick: its tick hot and cold, the wait between ticks, and
the Ed25519 work per state (a profiling aid beside bench/agent_profile.py, not a `covey bench`
section).

    python -m bench.agent_floor [--ticks 300]

In-process, on an injected clock: one `Agent` (sim backend, open mode, a router of its own and
nobody else) takes off and flies a long goto; then its tick's CPU (thread time) is measured
back to back ("hot": caches warm) and with a real 100 ms sleep before each tick, as a 10 Hz
agent runs ("cold": whatever else the machine ran since has evicted its code and data). The
cost of the sleep itself (`threading.Event.wait(0.1)`, what kit/ticks.py waits on) and of one
Ed25519 signature and verification (`cryptography`, a state's size) are measured alone.
Medians of `--repeats` runs, printed and written to bench/results/agent_floor.json.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time

from bench import common


def _agent_ticks(ticks: int, sleep_s: float) -> float:
    """CPU ms per tick of a flying agent, each tick after a `sleep_s` sleep."""
    from agent.backends.sim import SimBackend, SimConfig
    from agent.failsafe import FailsafeConfig
    from agent.hosts import Agent
    from agent.shell_config import AgentConfig
    from comms.mesh import Mesh
    from comms.schema import AckResult, Command, Mode
    from comms.session import embedded_router, free_tcp_port

    t = [0.0]
    with Mesh(embedded_router(free_tcp_port(), fleet="floor")) as mesh:
        cfg = AgentConfig(vehicle_id=1, failsafe=FailsafeConfig(require_gcs=False))
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
            cpu_s = 0.0
            for _ in range(ticks):
                if sleep_s:
                    time.sleep(sleep_s)
                t[0] += 0.1
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


def main(ticks: int = 300, repeats: int = 3) -> dict:
    hot, cold, wait, sign, verify = [], [], [], [], []
    for _ in range(repeats):
        hot.append(_agent_ticks(ticks, 0.0))
        cold.append(_agent_ticks(max(20, ticks // 10), 0.1))
        wait.append(_wait_us())
        s, v = _ed25519_us()
        sign.append(s)
        verify.append(v)
    med = statistics.median
    result = {
        "tick_hot_ms": med(hot),
        "tick_cold_ms": med(cold),
        "cold_over_hot": med(cold) / med(hot),
        "wait_100ms_us": med(wait),
        "ed25519_sign_us": med(sign),
        "ed25519_verify_us": med(verify),
        "repeats": repeats,
        "machine": common.machine(),
    }
    common.say(
        f"flying tick, 0 neighbours: hot {result['tick_hot_ms']:.3f} ms, after a 100 ms sleep "
        f"{result['tick_cold_ms']:.3f} ms ({result['cold_over_hot']:.2f}x); "
        f"Event.wait(0.1) {result['wait_100ms_us']:.0f} us; Ed25519 sign "
        f"{result['ed25519_sign_us']:.0f} us, verify {result['ed25519_verify_us']:.0f} us"
    )
    common.write_json("agent_floor", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=300, help="hot ticks per run (cold: a tenth)")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    if a.ticks < 20 or a.repeats < 1:
        ap.error("--ticks must be at least 20 and --repeats at least 1")
    main(a.ticks, a.repeats)
