"""Record and replay throughput: `python -m bench.record_throughput [--messages N] [--runs R]`.

Median over runs, in messages per second (64-byte VehicleStates, loopback, one process with
separate Zenoh sessions for the publisher, the recorder and the watcher):
- sink: McapSink alone (queue, MCAP writer, flushes) - the recorder's ceiling;
- record: a publisher sends N states as fast as it can, the Recorder records them over Zenoh;
  rate = recorded / (last - first receive), plus the share recorded;
- read: read_recording of the file;
- replay: play() at unlimited speed into the mesh; rate = published / elapsed, plus the share a
  subscriber received.
Writes bench/results/record.json.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path

from comms import keys
from comms.foxglove_channels import FoxgloveConfig
from comms.mesh import Mesh
from comms.record import McapSink, RecordConfig, Recorder, read_recording
from comms.replay import play, prepare
from comms.schema import VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port

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


def bench_record(
    path: Path, n: int, port: int, fleet: str, foxglove: bool = True
) -> tuple[float, float, float]:
    """(receive rate, share received, end-to-end rate: first receive -> file closed, i.e.
    with the writer thread's conversion and compression drained)."""
    stamps: list[int] = []
    fox = FoxgloveConfig() if foxglove else None
    with Mesh(embedded_peer(port, fleet=fleet)) as pub:
        rec = Recorder(RecordConfig(str(path), embedded_peer(port, fleet=fleet), foxglove=fox))
        orig = rec._on_sample

        def timed(sample):  # the receive times the rate is taken over
            stamps.append(time.perf_counter_ns())
            orig(sample)

        rec._entities[0].undeclare()
        rec._entities[0] = rec._session.declare_subscriber(keys.everything(fleet), timed)
        with rec:
            time.sleep(0.5)  # discovery
            for k in range(n):
                pub.publish_state(_state(k))
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
    return rate, got / n, end_to_end


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


def main(messages: int = 20_000, runs: int = 3) -> dict:
    port = free_tcp_port()
    rows: dict[str, list[float]] = {}
    with Mesh(embedded_router(port, fleet="bench")), tempfile.TemporaryDirectory() as tmp:
        for r in range(runs):
            fleet = "b" + uuid.uuid4().hex[:8]
            path = Path(tmp) / f"run{r}.mcap"
            rows.setdefault("sink_msgs_s", []).append(bench_sink(Path(tmp) / "sink.mcap", messages))
            for fox in (False, True):  # the same run, with and without Foxglove's channels
                tag = "_foxglove" if fox else "_covey_only"
                out = path if fox else Path(tmp) / f"run{r}{tag}.mcap"  # read/replay use `path`
                rate, share, e2e = bench_record(
                    out, messages, port, f"{fleet}{int(fox)}", foxglove=fox
                )
                rows.setdefault(f"record{tag}_msgs_s", []).append(rate)
                rows.setdefault(f"record{tag}_end_to_end_msgs_s", []).append(e2e)
                rows.setdefault(f"record{tag}_share", []).append(share)
                if fox:  # what a recording is by default
                    rows.setdefault("record_msgs_s", []).append(rate)
                    rows.setdefault("record_share", []).append(share)
            rows.setdefault("read_msgs_s", []).append(bench_read(path))
            rate, share = bench_replay(path, port, fleet + "r")
            rows.setdefault("replay_msgs_s", []).append(rate)
            rows.setdefault("replay_received_share", []).append(share)
    result = {
        "messages": messages,
        "runs": runs,
        "machine": platform.machine(),
        "python": platform.python_version(),
        "median": {k: statistics.median(v) for k, v in rows.items()},
        "all": rows,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=20_000)
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    res = main(a.messages, a.runs)
    for name, value in res["median"].items():
        unit = "msgs/s" if name.endswith("msgs_s") else "(share)"
        print(
            f"{name:24s} {value:12.1f} {unit}"
            if unit == "msgs/s"
            else f"{name:24s} {value:12.3f} {unit}"
        )
    print(f"wrote {RESULTS}")
