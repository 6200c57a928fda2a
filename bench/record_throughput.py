"""Record and replay throughput: `python -m bench.record_throughput [--messages N] [--runs R]`.

Median over runs, in messages per second (64-byte VehicleStates, loopback; the router and the
recorder in this process, the publisher in a child process of its own, as vehicles are):
- sink: McapSink alone (queue, MCAP chunks, flushes) - the recorder's ceiling;
- record: the publisher sends N states as fast as it can, the Recorder records them over Zenoh;
  rate = recorded / (last - first receive), plus the share recorded, and end to end = recorded /
  (first receive -> file closed, the standard channels written). Four ways in the same run:
  covey_only (--no-foxglove); foxglove (the standard channels made by the Foxglove worker
  process, what `covey record` does: held back while more than 4,000 messages/s arrive);
  foxglove_live (the worker handed every flush at once, to show why it is held back);
  foxglove_inline (made in the writer thread: the reference path, and how recording worked
  before the worker). worker_us_per_msg: the worker's CPU per state, its start (~0.15 s)
  included. The recorder's own CPU per state, without Zenoh's, is in bench/foxglove.py;
- paced: the same four ways at offered rates below the burst's (--paced-hz; 1,000 states/s is
  100 vehicles at 10 Hz, 6,500/s about half the burst's rate): the share recorded, which should
  be as much as covey_only's;
- read: read_recording of the file;
- replay: play() at unlimited speed into the mesh; rate = published / elapsed, plus the share a
  subscriber received.
Writes bench/results/record.json.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

from bench.common import children
from comms import keys
from comms.mesh import Mesh
from comms.schema import VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port
from recording.foxglove_channels import FoxgloveConfig
from recording.record import McapSink, RecordConfig, Recorder, read_recording
from recording.replay import play, prepare

RESULTS = Path(__file__).parent / "results" / "record.json"


def _state(k: int) -> VehicleState:
    return VehicleState(1 + k % 10, k, time.time_ns(), (k * 1e-3, 0.0, -5.0), (1.0, 0.0, 0.0), 0.0)


def bench_sink(path: Path, n: int) -> float:
    data = [(keys.state("bench", 1 + k % 10), _state(k).encode()) for k in range(n)]
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        sink = McapSink(f, "bench", 16 * 1024, 0.2)
        for k, (topic, payload) in enumerate(data):
            sink.put(topic, payload, k)
        sink.close()
    return n / (time.perf_counter() - t0)


MODES: dict[str, dict | None] = {
    "covey_only": None,
    "foxglove": {},
    "foxglove_live": {"foxglove_defer_hz": math.inf},
    "foxglove_inline": {"foxglove_worker": False},
}
"""Recording modes: name -> McapSink's Foxglove options (None = no standard channels)."""


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _publish(pub: Mesh, n: int, rate_hz: float | None) -> None:
    """n states, as fast as the publisher can (None) or paced at rate_hz in 5 ms steps."""
    if rate_hz is None:
        for k in range(n):
            pub.publish_state(_state(k))
        return
    t0, k = time.perf_counter(), 0
    while k < n:
        due = min(n, int((time.perf_counter() - t0) * rate_hz) + 1)
        while k < due:
            pub.publish_state(_state(k))
            k += 1
        time.sleep(0.005)


def publish_main(port: int, fleet: str, n: int, rate_hz: float | None) -> None:
    """The publisher, a process of its own as vehicles are (so that its Python loop shares no
    GIL with the recorder): join, let discovery settle, publish."""
    with Mesh(embedded_peer(port, fleet=fleet)) as pub:
        time.sleep(1.0)
        print("publishing", flush=True)
        _publish(pub, n, rate_hz)
        time.sleep(0.5)  # let the last puts leave before the session closes
    print("done", flush=True)


def bench_record(
    path: Path, n: int, port: int, fleet: str, mode: str, rate_hz: float | None = None
) -> dict[str, float]:
    """Receive rate, share received, end-to-end rate (first receive -> file closed, i.e. with
    the conversion and compression drained) and the Foxglove worker's CPU per state."""
    stamps: list[int] = []
    opts = MODES[mode]
    fox = FoxgloveConfig() if opts is not None else None
    kids0 = _children_cpu_s()
    with open(path, "wb") as f, children() as kids:
        sink = McapSink(f, fleet, 16 * 1024, 0.2, foxglove=fox, **(opts or {}))
        cfg = RecordConfig(str(path), embedded_peer(port, fleet=fleet), foxglove=fox)
        rec = Recorder(cfg, sink=sink)
        orig = rec._on_sample

        def timed(sample):  # the receive times the rate is taken over
            stamps.append(time.perf_counter_ns())
            orig(sample)

        rec._entities[0].undeclare()
        rec._entities[0] = rec._session.declare_subscriber(keys.everything(fleet), timed)
        with rec:
            args = ("--publish", str(port), fleet, str(n), str(rate_hz or 0))
            pub = kids.start("-m", "bench.record_throughput", *args)
            pub.wait_for("publishing")
            pub.wait_for("done", timeout_s=600.0)
            # reap it here, for its own CPU time (the worker's is the rest of our children's)
            _pid, _status, usage = os.wait4(pub.pid, 0)
            pub_cpu_s = usage.ru_utime + usage.ru_stime
            deadline = time.monotonic() + 10.0
            while len(stamps) < n and time.monotonic() < deadline:
                last = len(stamps)
                time.sleep(0.2)
                if len(stamps) == last:
                    break
        closed_ns = time.perf_counter_ns()  # `with rec` ended: the writer drained and closed
    got = len(stamps)
    rate = (got - 1) / ((stamps[-1] - stamps[0]) / 1e9) if got > 1 else 0.0
    end_to_end = got / ((closed_ns - stamps[0]) / 1e9) if got else 0.0
    return {
        "msgs_s": rate,
        "share": got / n,
        "end_to_end_msgs_s": end_to_end,
        "worker_us_per_msg": 1e6 * (_children_cpu_s() - kids0 - pub_cpu_s) / max(got, 1),
    }


def bench_read(path: Path) -> float:
    t0 = time.perf_counter()
    rec = read_recording(path)
    return len(rec.messages) / (time.perf_counter() - t0)


def bench_replay(path: Path, port: int, fleet: str) -> tuple[float, float]:
    items = prepare(read_recording(path))
    received = [0]
    lock = threading.Lock()

    def on_state(_s, _t):
        with lock:
            received[0] += 1

    with (
        Mesh(embedded_peer(port, fleet=fleet)) as watcher,
        Mesh(embedded_peer(port, fleet=fleet)) as out,
    ):
        watcher.subscribe_states(on_state)
        time.sleep(0.5)
        t0 = time.perf_counter()
        res = play(out, items, speed=math.inf)
        elapsed = time.perf_counter() - t0
        time.sleep(0.5)
    return res.states / elapsed, received[0] / max(res.states, 1)


def main(
    messages: int = 20_000, runs: int = 3, paced_hz: tuple[float, ...] = (), paced_s: float = 3.0
) -> dict:
    port = free_tcp_port()
    rows: dict[str, list[float]] = {}
    with Mesh(embedded_router(port, fleet="bench")), tempfile.TemporaryDirectory() as tmp:
        for r in range(runs):
            fleet = "b" + uuid.uuid4().hex[:8]
            path = Path(tmp) / f"run{r}.mcap"
            rows.setdefault("sink_msgs_s", []).append(bench_sink(Path(tmp) / "sink.mcap", messages))
            for k, mode in enumerate(MODES):  # the same run, with and without the channels
                out = path if mode == "foxglove" else Path(tmp) / f"run{r}{mode}.mcap"
                res = bench_record(out, messages, port, f"{fleet}{k}", mode)
                for key, value in res.items():
                    if key != "worker_us_per_msg" or mode in ("foxglove", "foxglove_live"):
                        rows.setdefault(f"record_{mode}_{key}", []).append(value)
                if mode == "foxglove":  # what a recording is by default (read/replay use it)
                    rows.setdefault("record_msgs_s", []).append(res["msgs_s"])
                    rows.setdefault("record_share", []).append(res["share"])
            for hz in paced_hz:  # an offered load below the burst's: is anything lost?
                for k, mode in enumerate(MODES):
                    res = bench_record(
                        Path(tmp) / "paced.mcap",
                        int(hz * paced_s),
                        port,
                        f"{fleet}p{int(hz)}{k}",
                        mode,
                        rate_hz=hz,
                    )
                    rows.setdefault(f"paced_{int(hz)}hz_{mode}_share", []).append(res["share"])
            rows.setdefault("read_msgs_s", []).append(bench_read(path))
            rate, share = bench_replay(path, port, fleet + "r")
            rows.setdefault("replay_msgs_s", []).append(rate)
            rows.setdefault("replay_received_share", []).append(share)
    med = {k: statistics.median(v) for k, v in rows.items()}
    for mode in ("foxglove", "foxglove_live", "foxglove_inline"):  # covey-only rate / rate
        for key in ("msgs_s", "end_to_end_msgs_s"):
            med[f"record_{mode}_{key}_cost_ratio"] = (
                med[f"record_covey_only_{key}"] / med[f"record_{mode}_{key}"]
            )
    result = {
        "messages": messages,
        "runs": runs,
        "paced_hz": list(paced_hz),
        "paced_s": paced_s,
        "machine": platform.machine(),
        "python": platform.python_version(),
        "median": med,
        "all": rows,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--publish":  # the publisher child of bench_record
        port, fleet, n, hz = sys.argv[2:6]
        publish_main(int(port), fleet, int(n), float(hz) or None)
        raise SystemExit(0)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=20_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument(
        "--paced-hz",
        default="1000,4000,6500",
        help="also publish at these rates (states/s, comma-separated; empty = none) ...",
    )
    ap.add_argument("--paced-s", type=float, default=3.0, help="... for this long each")
    a = ap.parse_args()
    paced = tuple(float(x) for x in a.paced_hz.split(",") if x.strip())
    res = main(a.messages, a.runs, paced, a.paced_s)
    for name, value in res["median"].items():
        unit = {"msgs_s": "msgs/s", "_share": "(share)", "_ratio": "x", "per_msg": "us"}
        unit = next((u for end, u in unit.items() if name.endswith(end)), "")
        print(f"{name:44s} {value:12.3f} {unit}")
    print(f"wrote {RESULTS}")
