"""Flood drill: does a rogue peer sending 10,000 bogus states/s disturb the agents' guidance tick?

    python -m bench.flood_jitter                      # baseline, then flood; prints p50/p99
    python -m bench.flood_jitter --duration-s 10 --rate-hz 10000
    python -m bench.flood_jitter flood --port P --rate-hz 10000 --duration-s 5   # the rogue alone

Two sim agents fly a goto (guidance and the policy run every tick) on an embedded mesh. The
receiver (this process) subscribes to their states; each state carries the agent's stamp, so the
interval between consecutive stamps of one agent is its tick period as the agent lived it
(10 Hz: 100 ms), independent of the receiver's own delays. Reported per run: interval p50/p99,
|interval - 100 ms| p50/p99 (the jitter), states missing by sequence number, delivery latency
(receive - stamp) p50/p99, and how many bogus messages the rogue sent.

The rogue mixes: malformed bytes on vehicle state keys, well-formed states whose id does not
match their key, and well-formed states of 1000 phantom vehicles 5 km away (they enter every
agent's neighbour table, which is the expensive part). `--mix feed` sends the phantoms to the
ground stations instead: feed batches (comms/feed.py) of FEED_FLOOD_ENTRIES phantom states each.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cli.options import renamed
from kit.procs import Child, python_env

REPO = Path(__file__).resolve().parent.parent
PERIOD_NS = 100_000_000
PHANTOM_IDS = range(1000, 2000)
FEED_FLOOD_ENTRIES = 50
"""Phantom states in each feed batch of `--mix feed` (one message)."""


@dataclass(frozen=True)
class FloodConfig:
    """What the rogue peer sends."""

    port: int
    """The embedded mesh's router port on 127.0.0.1."""
    rate_hz: float = 10_000.0
    """Bogus messages per second (all kinds together)."""
    seconds: float = 5.0
    fleet: str = "covey"
    seed: int = 1
    mix: str = "all"
    """all | malformed (bad bytes and spoofed ids only) | phantom (well-formed phantom vehicles
    only) | feed (phantoms in feed batches: what a ground station hears)."""


def bogus_messages(fleet: str, rng: random.Random, mix: str = "all"):
    """Endless (key, payload) pairs: malformed, mismatched and phantom states, mixed."""
    from comms import keys
    from comms.feed import split
    from comms.schema import FeedBatch, FeedEntry, VehicleState

    if mix == "feed":
        phantoms = bogus_messages(fleet, rng, "phantom")
        for feed_seq in range(1, 2**32):
            entries = [FeedEntry(feed_seq, next(phantoms)[1]) for _ in range(FEED_FLOOD_ENTRIES)]
            (run,) = split(entries)
            yield keys.feed(fleet, rng.choice(PHANTOM_IDS)), FeedBatch(feed_seq, run).encode()
    seq = 0
    while True:
        seq += 1
        r = rng.random()
        if mix == "malformed":
            r *= 0.5
        elif mix == "phantom":
            r = 0.5 + 0.5 * r
        if r < 0.3:  # malformed bytes on a real vehicle's key
            yield (
                keys.state(fleet, rng.choice((1, 2))),
                rng.randbytes(rng.choice((0, 1, 63, 64, 65, 200))),
            )
        elif r < 0.5:  # a well-formed state of vehicle 1 published on vehicle 2's key (spoof)
            s = VehicleState(
                1, seq & 0xFFFFFFFF, time.time_ns(), (0.0, 0.0, -3.0), (0.0, 0.0, 0.0), 0.0
            )
            yield keys.state(fleet, 2), s.encode()
        else:  # phantom vehicles far away
            vid = rng.choice(PHANTOM_IDS)
            ang = rng.uniform(0, 2 * np.pi)
            s = VehicleState(
                vid,
                seq & 0xFFFFFFFF,
                time.time_ns(),
                (5000.0 * np.cos(ang), 5000.0 * np.sin(ang), -3.0),
                (0.0, 0.0, 0.0),
                0.0,
            )
            yield keys.state(fleet, vid), s.encode()


def flood(cfg: FloodConfig) -> int:
    """Send for cfg.seconds at cfg.rate_hz in 10 ms batches; returns how many were sent."""
    import zenoh

    from comms.session import embedded_peer, open_session

    rng = random.Random(cfg.seed)
    gen = bogus_messages(cfg.fleet, rng, cfg.mix)
    sent = 0
    with open_session(embedded_peer(cfg.port, fleet=cfg.fleet)) as session:
        pubs: dict[str, zenoh.Publisher] = {}
        t0 = time.monotonic()
        batch = max(1, int(cfg.rate_hz / 100))
        while (now := time.monotonic()) - t0 < cfg.seconds:
            for _ in range(batch):
                key, payload = next(gen)
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.DROP
                    )
                pub.put(payload)
                sent += 1
            due = t0 + sent / cfg.rate_hz
            if due > now:
                time.sleep(due - now)
    return sent


@dataclass
class Samples:
    """Per-vehicle (seq, stamp_ns, recv_ns) of every state received."""

    by_vehicle: dict[int, list[tuple[int, int, int]]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_state(self, s, recv_ns: int) -> None:
        if s.vehicle_id in (1, 2):
            with self.lock:
                self.by_vehicle.setdefault(s.vehicle_id, []).append((s.seq, s.stamp_ns, recv_ns))

    def clear(self) -> None:
        with self.lock:
            self.by_vehicle.clear()


def summarise(samples: Samples) -> dict:
    intervals, latencies, missing, received = [], [], 0, 0
    with samples.lock:
        data = {v: sorted(x) for v, x in samples.by_vehicle.items()}
    for rows in data.values():
        received += len(rows)
        for (s0, t0, _), (s1, t1, _) in zip(rows, rows[1:], strict=False):
            missing += s1 - s0 - 1
            if s1 == s0 + 1:
                intervals.append(t1 - t0)
        latencies += [r - t for _, t, r in rows]
    iv = np.array(intervals, dtype=float) / 1e6
    lat = np.array(latencies, dtype=float) / 1e6
    jit = np.abs(iv - PERIOD_NS / 1e6)

    def pct(a, q):
        return round(float(np.percentile(a, q)), 2) if a.size else None

    return {
        "states": received,
        "missing_by_seq": missing,
        "interval_ms_p50": pct(iv, 50),
        "interval_ms_p99": pct(iv, 99),
        "interval_ms_max": pct(iv, 100),
        "jitter_ms_p50": pct(jit, 50),
        "jitter_ms_p99": pct(jit, 99),
        "latency_ms_p50": pct(lat, 50),
        "latency_ms_p99": pct(lat, 99),
    }


def start_agents(port: int, ids=(1, 2)) -> list[Child]:
    """Agents flying sim vehicles on the mesh at `port` (stopped by the caller: `a.stop()`)."""
    env = python_env(REPO, OMP_WAIT_POLICY="PASSIVE", OPENBLAS_NUM_THREADS="1")
    return [
        Child(
            [
                sys.executable,
                "-m",
                "covey_cli",
                "agent",
                "--id",
                str(v),
                "--connect",
                f"tcp/127.0.0.1:{port}",
                f"--start-ne-m=0,{4 * v}",
                "--no-gcs-failsafe",
                # a state every tick, landed too: the stream whose gaps and jitter are measured
                "--idle-state-hz",
                "10",
            ],
            cwd=REPO,
            env=env,
            output="discard",
            stderr="discard",
        ).start()
        for v in ids
    ]


def start_flooder(port: int, rate_hz: float, seconds: float, mix: str = "all") -> Child:
    """The rogue (`flood` mode) for `seconds`; `wait_output()` is its FLOOD line."""
    return Child(
        [
            sys.executable,
            "-m",
            "bench.flood_jitter",
            "flood",
            "--port",
            str(port),
            "--rate-hz",
            str(rate_hz),
            "--duration-s",
            str(seconds),
            "--mix",
            mix,
        ],
        cwd=REPO,
        env=python_env(REPO),
        stderr="inherit",
    ).start()


def fly(mesh, ids=(1, 2)) -> None:
    """Take off and start a long goto so that guidance runs every tick."""
    from comms.commands import new_nonce
    from comms.schema import Command

    res = mesh.send_command(
        Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=0), expect=ids, timeout_s=5
    )
    if not res.ok:
        raise RuntimeError(f"takeoff: {res.summary()}")
    time.sleep(2.5)
    for v in ids:
        mesh.send_command(
            Command.goto_local(200.0, 4.0 * v, -3.0, nonce=new_nonce(), stamp_ns=0, targets=(v,)),
            timeout_s=5,
        )


def run(seconds: float, rate_hz: float, mix: str = "all", out=print) -> dict:
    """Baseline for `seconds`, then a flood for `seconds`, on one fleet of two agents."""
    from comms.mesh import Mesh
    from comms.session import embedded_router, free_tcp_port

    port = free_tcp_port()
    started: list[Child] = []  # stopped however this ends
    results = {}
    try:
        with Mesh(embedded_router(port)) as mesh:
            samples = Samples()
            mesh.subscribe_states(samples.on_state)
            presence = mesh.presence()
            agents = start_agents(port)
            started += agents
            if not presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60):
                raise RuntimeError("agents did not come up")
            fly(mesh)
            time.sleep(1.0)
            samples.clear()
            time.sleep(seconds)
            results["baseline"] = summarise(samples)
            out(f"baseline: {results['baseline']}")
            samples.clear()
            errors0 = mesh.stats.decode_errors
            rogue = start_flooder(port, rate_hz, seconds + 1.0, mix)
            started.append(rogue)
            time.sleep(0.5)
            samples.clear()
            time.sleep(seconds)
            results["flood"] = summarise(samples)
            sent_line = rogue.wait_output(timeout_s=30).strip()
            results["flood"]["rogue"] = sent_line
            results["flood"]["decode_errors_at_receiver"] = mesh.stats.decode_errors - errors0
            results["flood"]["agents_alive"] = all(a.poll() is None for a in agents)
            out(f"flood:    {results['flood']}")
    finally:
        for child in started:
            child.stop(grace_s=0.0)
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bench.flood_jitter",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("mode", nargs="?", choices=("run", "flood"), default="run")
    p.add_argument(
        "--duration-s", type=float, default=10.0, help="length of the baseline and of the flood"
    )
    p.add_argument("--rate-hz", type=float, default=10_000.0, help="bogus messages per second")
    renamed(p, {"--seconds": "--duration-s", "--rate": "--rate-hz"})
    p.add_argument("--port", type=int, default=None, help="flood mode: the mesh's router port")
    p.add_argument(
        "--mix",
        choices=("all", "malformed", "phantom", "feed"),
        default="all",
        help="what the rogue sends",
    )
    p.add_argument("--json", default=None, help="also write the results here")
    args = p.parse_args(argv)
    if not 0 < args.duration_s <= 600 or not 0 < args.rate_hz <= 1e6:
        p.error("--duration-s must be within (0, 600] and --rate-hz within (0, 1e6]")
    if args.mode == "flood":
        if args.port is None:
            p.error("flood needs --port")
        t0 = time.monotonic()
        n = flood(
            FloodConfig(port=args.port, rate_hz=args.rate_hz, seconds=args.duration_s, mix=args.mix)
        )
        print(
            f"FLOOD sent {n} in {time.monotonic() - t0:.1f} s ({n / (time.monotonic() - t0):.0f}/s)",
            flush=True,
        )
        return 0
    results = run(args.duration_s, args.rate_hz, args.mix)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
