"""Foxglove channels: what they cost. `python -m bench.foxglove [--quick] [--runs R] [--live-s S]`

- record: McapSink (the recorder's writer thread: queue, MCAP chunks, zstd, flushes) fed the same
  traffic three ways, median of R runs, all in the same run:
    off     covey's channels only;
    worker  + the standard channels, made in the Foxglove worker process (what `covey record` does);
    inline  + the standard channels, made in the writer thread (the reference path; how recording
            worked before the worker).
  hot: covey messages per CPU second of the recorder's process (every thread of it: writer, the
  worker's pipe threads, and the put loop, the same in every mode); worker: the child's CPU per
  message, less its start (an idle worker's CPU, measured apart); wall: first put -> file closed;
- size: file bytes per vehicle-hour both ways, 10 vehicles at 10 Hz for 120 s of log time;
- live: `covey foxglove` as a child process serving 100 vehicles publishing at 10 Hz; its CPU share
  (of one core) and the latency from a state's stamp to a WebSocket client decoding its pose.
Writes bench/results/foxglove.json. `--figure flight.mcap` instead draws a recording's standard
channels with matplotlib (docs/foxglove_view.png), decoded with protobuf as Foxglove decodes them.
"""

from __future__ import annotations

import argparse
import io
import json
import resource
import statistics
import threading
import time
import uuid
from pathlib import Path

from mcap.reader import make_reader

from bench.common import DOCS, children, cpu_seconds, pct, pyplot, say, write_json
from comms import keys
from comms.mesh import Mesh
from comms.schema import Event, Mode, VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port
from recording.foxglove_channels import POSE_IN_FRAME, FoxgloveConfig
from recording.record import McapSink

VEHICLES, RATE_HZ, LOG_S = 10, 10.0, 120.0


def proto_class(name: str, fds: bytes):
    """The class protobuf builds from a FileDescriptorSet (protobuf is in the test extra)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(fds).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def _traffic(n_vehicles: int, rate_hz: float, duration_s: float) -> list[tuple[str, bytes, int]]:
    """A fleet circling: states at rate_hz, an event per vehicle every 10 s."""
    out = []
    t0 = 1_700_000_000_000_000_000
    for k in range(int(duration_s * rate_hz)):
        t_ns = t0 + int(k / rate_hz * 1e9)
        for v in range(1, n_vehicles + 1):
            s = VehicleState(
                v,
                k,
                t_ns,
                (v + 0.01 * k, 0.02 * k, -5.0),
                (1.0, 2.0, 0.0),
                0.5,
                mode=Mode.GOTO,
                armed=True,
            )
            out.append((keys.state("bench", v), s.encode(), t_ns + 1_000_000))
            if k % int(10 * rate_hz) == 0:
                out.append((keys.event("bench", v), Event(v, t_ns, "waypoint").encode(), t_ns))
    return out


def _children_cpu_s() -> float:
    """CPU seconds of this process's children that have ended (the Foxglove workers)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


MODES = ("off", "worker", "inline")


def bench_sink(traffic, mode: str) -> dict:
    """One pass of `traffic` through McapSink in `mode` (see the module docstring)."""
    buf = io.BytesIO()
    fox = None if mode == "off" else FoxgloveConfig()
    kids0, cpu0, t0 = _children_cpu_s(), time.process_time(), time.perf_counter()
    sink = McapSink(buf, "bench", 16 * 1024, 0.2, foxglove=fox, foxglove_worker=mode == "worker")
    for topic, data, recv_ns in traffic:
        sink.put(topic, data, recv_ns)
    sink.close()
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - cpu0
    return {
        "hot_msgs_per_cpu_s": len(traffic) / cpu_s,
        "wall_msgs_s": len(traffic) / wall_s,
        "worker_cpu_s": _children_cpu_s() - kids0,
        "bytes": len(buf.getvalue()),
        "foxglove_messages": sink.counts.get("foxglove", 0),
    }


def bench_live(duration_s: float, n_vehicles: int = 100, rate_hz: float = 10.0) -> dict:
    from websockets.sync.client import connect

    pose_cls = proto_class(POSE_IN_FRAME.name, POSE_IN_FRAME.data)
    port, fleet = free_tcp_port(), "fx" + uuid.uuid4().hex[:6]
    latencies_ms: list[float] = []
    with Mesh(embedded_router(port, fleet=fleet)) as router, children() as kids:
        bridge = kids.start(
            "-m",
            "covey_cli",
            "foxglove",
            "--port",
            "0",
            "--fleet",
            fleet,
            "--connect",
            f"tcp/127.0.0.1:{port}",
        )
        ws_port = int(bridge.wait_for("foxglove bridge: ").split(":")[-1].split()[0])
        stop = threading.Event()

        def publish() -> None:
            with Mesh(embedded_peer(port, fleet=fleet)) as pub:
                k = 0
                next_s = time.monotonic()
                while not stop.is_set():
                    for v in range(1, n_vehicles + 1):
                        pub.publish_state(
                            VehicleState(
                                v, k, time.time_ns(), (v, 0.01 * k, -5.0), (1.0, 0.0, 0.0), 0.0
                            )
                        )
                    k += 1
                    next_s += 1 / rate_hz
                    time.sleep(max(0.0, next_s - time.monotonic()))

        with connect(
            f"ws://127.0.0.1:{ws_port}",
            subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
            max_size=None,
        ) as ws:
            pub_thread = threading.Thread(target=publish, daemon=True)
            pub_thread.start()
            subs, n_ids = {}, 0
            warm_s, t_end = time.monotonic() + 3.0, time.monotonic() + 3.0 + duration_s
            cpu0 = wall0 = None
            while time.monotonic() < t_end:
                if cpu0 is None and time.monotonic() >= warm_s:  # discovery and subscriptions done
                    cpu0, wall0 = cpu_seconds(bridge.pid), time.monotonic()
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    new = []
                    for ch in msg.get("channels", []) if msg.get("op") == "advertise" else []:
                        if ch["topic"].endswith("/pose"):
                            n_ids += 1
                            subs[n_ids] = ch["topic"]
                            new.append({"id": n_ids, "channelId": ch["id"]})
                    if new:
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif frame[0] == 0x01 and cpu0 is not None:
                    ts = pose_cls.FromString(frame[13:]).timestamp
                    latencies_ms.append((time.time_ns() - (ts.seconds * 10**9 + ts.nanos)) / 1e6)
            cpu_share = (cpu_seconds(bridge.pid) - cpu0) / (time.monotonic() - wall0)
            stop.set()
            pub_thread.join(5)
        del router
    expected = n_vehicles * rate_hz * duration_s
    return {
        "vehicles": n_vehicles,
        "rate_hz": rate_hz,
        "seconds": duration_s,
        "bridge_cpu_share_of_one_core": cpu_share,
        "poses_received_share": len(latencies_ms) / expected,
        "latency_ms_p50": pct(latencies_ms, 50),
        "latency_ms_p95": pct(latencies_ms, 95),
        "latency_ms_max": max(latencies_ms, default=float("nan")),
    }


def read_standard(path: str | Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log_time_ns, decoded message)] for the protobuf and JSON channels."""
    out: dict[str, list] = {}
    classes: dict[int, object] = {}
    with open(path, "rb") as f:
        for sch, ch, msg in make_reader(f).iter_messages():
            if ch.message_encoding == "protobuf":
                if sch.id not in classes:
                    classes[sch.id] = proto_class(sch.name, sch.data)
                out.setdefault(ch.topic, []).append(
                    (msg.log_time, classes[sch.id].FromString(msg.data))
                )
            elif ch.message_encoding == "json":
                out.setdefault(ch.topic, []).append((msg.log_time, json.loads(msg.data)))
    return out


def figure(path: str | Path, out_png: Path) -> Path:
    """Draw a recording's standard channels in the docs layout's arrangement (3D from above,
    Map, Plot, Log): a stand-in for a Foxglove screenshot, from what Foxglove would decode."""
    std = read_standard(path)
    plt = pyplot()
    fig, ((ax3d, axmap), (axplot, axlog)) = plt.subplots(2, 2, figsize=(12, 9))
    vids = sorted(int(t.split("/")[2]) for t in std if t.endswith("/pose"))
    t0 = min(ts for t in std for ts, _ in std[t])
    for vid in vids:
        poses = [m.pose.position for _, m in std[f"/vehicles/{vid}/pose"]]
        times = [(ts - t0) / 1e9 for ts, _ in std[f"/vehicles/{vid}/pose"]]
        (line,) = ax3d.plot(
            [p.y for p in poses], [p.x for p in poses], lw=1, label=f"vehicle {vid}"
        )
        fixes = [m for _, m in std[f"/vehicles/{vid}/fix"]]
        axmap.plot(
            [f.longitude for f in fixes], [f.latitude for f in fixes], lw=1, color=line.get_color()
        )
        axplot.plot(times, [-p.z for p in poses], lw=1, color=line.get_color())
    # the last scene entity of each vehicle: body coloured by mode, separation ring
    last = {}
    for _, upd in std.get("/scene", []):
        for ent in upd.entities:
            last[ent.id] = ent
    for ent in last.values():
        cube, ring = ent.cubes[0], ent.cylinders[0]
        c = (cube.color.r, cube.color.g, cube.color.b)
        ax3d.plot(cube.pose.position.y, cube.pose.position.x, "s", color=c, ms=8)
        ax3d.add_patch(
            plt.Circle(
                (ring.pose.position.y, ring.pose.position.x),
                ring.size.x / 2,
                fill=False,
                color=(ring.color.r, ring.color.g, ring.color.b),
            )
        )
    ax3d.set(
        title="3D (/scene, /vehicles/*/pose), from above",
        xlabel="east m",
        ylabel="north m",
        aspect="equal",
    )
    ax3d.legend(fontsize=7)
    axmap.set(title="Map (/vehicles/*/fix)", xlabel="longitude deg", ylabel="latitude deg")
    axmap.ticklabel_format(useOffset=False)
    axplot.set(title="Plot: altitude (-pose.position.z)", xlabel="s", ylabel="m")
    lines = [
        f"{(ts - t0) / 1e9:6.1f}s  {m.name:10s} {m.message}" for ts, m in std.get("/events", [])
    ]
    lines += [
        f"{(ts - t0) / 1e9:6.1f}s  ack vehicle/{a['vehicle_id']} {a['command_kind']} {a['result']}"
        for ts, a in std.get("/acks", [])
    ]
    lines.sort()
    axlog.axis("off")
    axlog.set_title("Log (/events) and /acks")
    axlog.text(
        0,
        1,
        "\n".join(lines[:28]),
        va="top",
        family="monospace",
        fontsize=7,
        transform=axlog.transAxes,
    )
    fig.tight_layout()
    fig.savefig(out_png, dpi=80)
    return out_png


def main(quick: bool = False, runs: int = 3, live_s: float = 10.0) -> dict:
    if quick:
        runs, live_s = 1, 4.0
    traffic = _traffic(VEHICLES, RATE_HZ, LOG_S)
    rows: dict[str, list[float]] = {}
    sizes, made = {}, {}
    start_cpu_s = []
    for r in range(runs):
        say(f"record run {r + 1}/{runs} ({len(traffic)} messages)")
        start_cpu_s.append(bench_sink([], "worker")["worker_cpu_s"])
        for mode in MODES:  # interleaved, so that the machine's load falls on each alike
            res = bench_sink(traffic, mode)
            rows.setdefault(f"{mode}_hot_msgs_per_cpu_s", []).append(res["hot_msgs_per_cpu_s"])
            rows.setdefault(f"{mode}_wall_msgs_s", []).append(res["wall_msgs_s"])
            sizes[mode], made[mode] = res["bytes"], res["foxglove_messages"]
            if mode == "worker":
                rows.setdefault("worker_child_us_per_msg", []).append(
                    1e6 * (res["worker_cpu_s"] - start_cpu_s[-1]) / len(traffic)
                )
    med = {k: statistics.median(v) for k, v in rows.items()}
    med["worker_start_cpu_s"] = statistics.median(start_cpu_s)
    for mode in ("worker", "inline"):  # the cost asked about: with / without, same run
        med[f"{mode}_hot_cost_ratio"] = (
            med["off_hot_msgs_per_cpu_s"] / med[f"{mode}_hot_msgs_per_cpu_s"]
        )
    vehicle_h = VEHICLES * LOG_S / 3600
    live = None
    if live_s > 0:
        say(f"live bridge: 100 vehicles at 10 Hz for {live_s:g} s")
        live = bench_live(live_s)
    result = {
        "record": med,
        "record_all": rows,
        "covey_messages": len(traffic),
        "foxglove_messages": made,
        "bytes_per_vehicle_hour": {k: v / vehicle_h for k, v in sizes.items()},
        "live": live,
    }
    write_json("foxglove", result)
    return result


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--live-s", type=float, default=10.0, help="0 = no live-bridge run")
    ap.add_argument("--quick", action="store_true", help="one run, a 4 s live window")
    ap.add_argument(
        "--figure",
        metavar="MCAP",
        default=None,
        help="instead: draw this recording's standard channels to docs/foxglove_view.png",
    )
    a = ap.parse_args(argv)
    if a.figure:
        print(f"wrote {figure(a.figure, DOCS / 'foxglove_view.png')}")
        return 0
    res = main(a.quick, a.runs, a.live_s)
    rec, size, live = res["record"], res["bytes_per_vehicle_hour"], res["live"]
    print(f"record, medians of {a.runs}, {res['covey_messages']} covey messages:")
    print(
        f"{'':8s} {'msg/CPU-s (recorder)':>21s} {'cost x':>7s} {'msg/s wall':>11s} {'MB/veh-h':>9s}"
    )
    for mode in MODES:
        ratio = rec.get(f"{mode}_hot_cost_ratio", 1.0)
        print(
            f"{mode:8s} {rec[f'{mode}_hot_msgs_per_cpu_s']:21.0f} {ratio:7.2f} "
            f"{rec[f'{mode}_wall_msgs_s']:11.0f} {size[mode] / 1e6:9.2f}"
        )
    print(
        f"worker process: {rec['worker_child_us_per_msg']:.1f} us CPU per covey message, "
        f"{rec['worker_start_cpu_s']:.2f} s CPU to start"
    )
    if live is None:
        return 0
    cpu = 100 * live["bridge_cpu_share_of_one_core"]
    print(
        f"live bridge, {live['vehicles']} vehicles at {live['rate_hz']:g} Hz: CPU {cpu:.0f} % "
        f"of one core, latency p50 {live['latency_ms_p50']:.1f} ms "
        f"p95 {live['latency_ms_p95']:.1f} ms, "
        f"{100 * live['poses_received_share']:.0f} % of poses received"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
