"""What a state heard costs its receiver in Zenoh alone: one wake-up per message, unless the
messages come together (a `covey bench` section, skipped in --quick; about 90 s).

    python -m bench.zenoh_wakeups [--publishers 20] [--rate-hz 10] [--window-s 8] [--repeats 2]

A `covey router` on loopback; a publisher process puts `--publishers` 200-byte messages, each
on its own key, `--rate-hz` times a second, either all at once each period ("burst": what a
host of many vehicles sends) or each at a phase of its own, evenly over the period ("spread":
what separate vehicles send); a receiver process, polled at 10 Hz as an agent drains its states
(a Zenoh RingChannel, comms/mesh.py CellSubscription), counts them. The receiver's CPU per
second is measured with Zenoh's default thread pools and with the agent's (comms/session.py
AGENT_RUNTIME: the receive pool hands over to the application worker). Medians of `--repeats`
alternating runs, printed and written to bench/results/zenoh_wakeups.json.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import threading
import time

from bench import common
from kit.procs import python_env

PAYLOAD_BYTES = 200
"""About a signed VehicleState with its link tags."""
POLL_HZ = 10.0


def _session(port: int):

    from comms.session import MeshConfig, open_session

    return open_session(MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))


def role_receiver(port: int, window_s: float) -> None:
    """Drain everything under b/** at POLL_HZ for `window_s` (after 1 s to settle); print the
    messages and the process's CPU ms per second."""
    import zenoh

    with _session(port) as s:
        sub = s.declare_subscriber("b/**", zenoh.handlers.RingChannel(4096))
        print("READY", flush=True)
        wait = threading.Event()
        time.sleep(1.0)
        while sub.try_recv() is not None:
            pass
        n, c0, t0 = 0, time.process_time(), time.monotonic()
        while time.monotonic() - t0 < window_s:
            wait.wait(1.0 / POLL_HZ)
            while sub.try_recv() is not None:
                n += 1
        cpu_ms_per_s = (time.process_time() - c0) * 1e3 / (time.monotonic() - t0)
        print(f"RESULT {n} {cpu_ms_per_s:.3f}", flush=True)


def role_publisher(port: int, publishers: int, rate_hz: float, spread: bool) -> None:
    """Put one message per key per period until stopped."""
    with _session(port) as s:
        import zenoh

        pubs = [
            s.declare_publisher(f"b/{i}", congestion_control=zenoh.CongestionControl.DROP)
            for i in range(publishers)
        ]
        payload = bytes(PAYLOAD_BYTES)
        print("READY", flush=True)
        period_s, next_s = 1.0 / rate_hz, time.monotonic()
        while True:
            for k, pub in enumerate(pubs):
                if spread:
                    time.sleep(max(0.0, next_s + k * period_s / publishers - time.monotonic()))
                pub.put(payload)
            next_s += period_s
            time.sleep(max(0.0, next_s - time.monotonic()))


def one_run(publishers: int, rate_hz: float, spread: bool, agent_pools: bool, window_s: float):
    """(messages per second received, receiver CPU ms per second) of one run."""
    from comms.session import AGENT_RUNTIME, RUNTIME_ENV

    with common.children() as kids:
        (_router, port), *_ = common.start_routers(kids, 1)
        env = python_env(common.REPO)
        env.pop(RUNTIME_ENV, None)
        if agent_pools:
            env[RUNTIME_ENV] = AGENT_RUNTIME
        rx = kids.start(
            "-m",
            "bench.zenoh_wakeups",
            "--role",
            "receiver",
            "--port",
            str(port),
            "--window-s",
            str(window_s),
            env=env,
        )
        rx.wait_for("READY", 30)
        pub = kids.start(
            "-m",
            "bench.zenoh_wakeups",
            "--role",
            "publisher",
            "--port",
            str(port),
            "--publishers",
            str(publishers),
            "--rate-hz",
            str(rate_hz),
            *(["--spread"] if spread else []),
        )
        pub.wait_for("READY", 30)
        line = rx.wait_for("RESULT", window_s + 30)
    _, n, cpu = line.split()
    return int(n) / window_s, float(cpu)


def main(publishers: int, rate_hz: float, window_s: float, repeats: int) -> dict:
    cases = list(itertools.product((False, True), (False, True)))  # (spread, agent pools)
    got: dict[tuple[bool, bool], list[tuple[float, float]]] = {c: [] for c in cases}
    for _ in range(repeats):
        for spread, pools in cases:
            got[(spread, pools)].append(one_run(publishers, rate_hz, spread, pools, window_s))
            hz, cpu = got[(spread, pools)][-1]
            common.say(
                f"{'spread' if spread else 'burst '} {'agent pools ' if pools else 'Zenoh pools'}:"
                f" {hz:.0f} msgs/s, receiver {cpu:.1f} ms CPU a second"
            )
    rows = []
    for spread, pools in cases:
        runs = got[(spread, pools)]
        cpu = statistics.median(c for _, c in runs)
        hz = statistics.median(h for h, _ in runs)
        rows.append(
            {
                "arrival": "spread" if spread else "burst",
                "pools": "agent (receive on the application worker)" if pools else "Zenoh's",
                "msgs_per_s": hz,
                "receiver_cpu_ms_per_s": cpu,
                "receiver_cpu_us_per_msg": cpu * 1e3 / hz if hz else None,
                "runs_cpu_ms_per_s": [c for _, c in runs],
            }
        )
    result = {
        "publishers": publishers,
        "rate_hz": rate_hz,
        "payload_bytes": PAYLOAD_BYTES,
        "poll_hz": POLL_HZ,
        "window_s": window_s,
        "repeats": repeats,
        "rows": rows,
    }
    for r in rows:
        print(
            f"{r['arrival']:6s} {r['pools']:42s} {r['msgs_per_s']:6.0f} msgs/s  "
            f"{r['receiver_cpu_ms_per_s']:5.1f} ms CPU a second  "
            f"({r['receiver_cpu_us_per_msg']:.0f} us a message)"
        )
    common.write_json("zenoh_wakeups", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", default="bench", choices=["bench", "receiver", "publisher"])
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--publishers", type=int, default=20)
    ap.add_argument("--rate-hz", type=float, default=10.0)
    ap.add_argument("--window-s", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--spread", action="store_true", help="publisher: each key at its own phase")
    a = ap.parse_args()
    if not (1 <= a.publishers <= 200 and 0 < a.rate_hz <= 100 and a.window_s > 0 and a.repeats > 0):
        ap.error("--publishers 1..200, --rate-hz in (0, 100], --window-s and --repeats positive")
    if a.role == "receiver":
        role_receiver(a.port, a.window_s)
    elif a.role == "publisher":
        role_publisher(a.port, a.publishers, a.rate_hz, a.spread)
    else:
        sys.exit(0 if main(a.publishers, a.rate_hz, a.window_s, a.repeats) else 1)
