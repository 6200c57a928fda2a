"""Mesh latency and delivery at fleet scale, next to raw Zenoh doing the same traffic.

    python -m bench.mesh [--quick]           # writes mesh.json and mesh.png

Every measurement runs in separate processes on loopback: one hub (the embedded router, as a
ground station would be) that measures, and two publisher or responder processes that connect
to it as peers.
- states: n vehicles at 10 Hz, each state stamped just before it is sent; the hub measures
  receive-time minus stamp (in its callback, after covey's decode and checks) and the share of
  states delivered over a fixed window. "raw" sends the same 64-byte payloads on the same keys
  through bare Zenoh publishers/subscribers with the same options; "raw-batched" is the same
  without Zenoh's express flag (Zenoh may batch); "fleet-sim" is covey with the vehicles
  simulated by two `covey fleet-sim` processes.
- commands: one broadcast command to all n vehicles, time until every ack is in (covey:
  `Mesh.send_command` to `Mesh.serve_commands` handlers; raw: a `get` on the same wildcard key
  with same-size payloads, answered by bare queryables).
The other roles (`--role hub|pub|resp`) are this module run as a child process.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np

from bench import common
from comms import keys
from comms.session import MeshConfig, embedded_peer, embedded_router, free_tcp_port
from kit.procs import ChildGroup

FLEET = "bench"
RATE_HZ = 10.0
STATE_BYTES = 64
CMD_BYTES = 115  # a broadcast Command: 51-byte header, no targets, 64-byte signature
ACK_BYTES = 182


# -- child roles --------------------------------------------------------------------------------
def _ids(first: int, count: int) -> list[int]:
    return list(range(first, first + count))


def member(port: int, connect: str | None = None, hub: bool = False) -> MeshConfig:
    """A role's mesh: the hub hosts the embedded router on `port`, a publisher or responder is
    a peer of it; given `connect`, every role is a client of that router (bench/routers.py)."""
    if connect is not None:
        return MeshConfig(fleet=FLEET, mode="client", connect=(connect,))
    return embedded_router(port, fleet=FLEET) if hub else embedded_peer(port, fleet=FLEET)


def role_pub(kind: str, cfg: MeshConfig, first: int, count: int) -> None:
    """Publish `count` vehicles' states at RATE_HZ until killed."""
    import zenoh

    from comms.mesh import Mesh
    from comms.schema import Mode, VehicleState

    ids = _ids(first, count)
    stop = threading.Event()
    with Mesh(cfg) as mesh:
        if kind != "covey":  # raw: covey's publisher options; raw-batched: Zenoh may batch
            sess = mesh.session  # the same session config; bare Zenoh from here on
            express = kind == "raw"
            pubs = [
                sess.declare_publisher(
                    keys.state(FLEET, v),
                    congestion_control=zenoh.CongestionControl.DROP,
                    express=express,
                )
                for v in ids
            ]
            tmpl = [
                bytearray(VehicleState(v, 0, 0, (1.0, 2.0, -3.0), (0.1, 0.2, 0.0), 0.5).encode())
                for v in ids
            ]
        print("READY", flush=True)
        period_s, next_s, seq = 1.0 / RATE_HZ, time.monotonic(), 0
        while not stop.is_set():
            seq += 1
            for k, v in enumerate(ids):
                if kind != "covey":
                    buf = tmpl[k]
                    buf[4:16] = seq.to_bytes(4, "little") + time.time_ns().to_bytes(8, "little")
                    pubs[k].put(bytes(buf))
                else:
                    mesh.publish_state(
                        VehicleState(
                            v,
                            seq,
                            time.time_ns(),
                            (1.0, 2.0, -3.0),
                            (0.1, 0.2, 0.0),
                            0.5,
                            mode=Mode.HOLDING,
                            armed=True,
                        )
                    )
            next_s += period_s
            stop.wait(max(0.0, next_s - time.monotonic()))


def role_resp(kind: str, cfg: MeshConfig, first: int, count: int) -> None:
    """Answer commands for `count` vehicles until killed."""
    from comms.mesh import Mesh
    from comms.schema import AckResult, CommandAck, Mode

    with Mesh(cfg) as mesh:
        for v in _ids(first, count):
            if kind == "raw":
                ack = bytes(ACK_BYTES)
                mesh.session.declare_queryable(
                    keys.cmd(FLEET, v), lambda q, k=keys.cmd(FLEET, v), a=ack: q.reply(k, a)
                )
            else:
                mesh.serve_commands(
                    v,
                    lambda c, v=v: CommandAck(
                        v, c.nonce, mesh.clock_ns(), AckResult.ACCEPTED, "", Mode.LANDED
                    ),
                )
                mesh.declare_vehicle(v)
        print("READY", flush=True)
        threading.Event().wait()


def role_hub_states(kind: str, cfg: MeshConfig, n: int, window_s: float) -> dict:
    from comms.mesh import Mesh

    lock = threading.Lock()
    seen: set[int] = set()
    rows: list[tuple[int, int, int, int]] = []  # (recv_ns, stamp_ns, vehicle id, seq)
    all_seen = threading.Event()

    def record(vid: int, seq: int, stamp_ns: int) -> None:
        now = time.time_ns()
        with lock:
            rows.append((now, stamp_ns, vid, seq))
            if not all_seen.is_set():
                seen.add(vid)
                if len(seen) >= n:
                    all_seen.set()

    with Mesh(cfg) as mesh:
        if kind != "covey":
            mesh.session.declare_subscriber(
                keys.all_states(FLEET),
                lambda s: (
                    lambda b: record(
                        int.from_bytes(b[2:4], "little"),
                        int.from_bytes(b[4:8], "little"),
                        int.from_bytes(b[8:16], "little"),
                    )
                )(s.payload.to_bytes()),
            )
        else:
            mesh.subscribe_states(lambda s, _t: record(s.vehicle_id, s.seq, s.stamp_ns))
        print("READY", flush=True)
        if not all_seen.wait(90.0):
            return {"error": f"saw {len(seen)} of {n} vehicles"}
        time.sleep(1.0)  # let every publisher settle into its rhythm
        t0, cpu0 = time.time_ns(), time.process_time()
        time.sleep(window_s)
        t1, cpu1 = time.time_ns(), time.process_time()
        with lock:
            got = np.array([r for r in rows if t0 <= r[0] < t1], dtype=np.int64).reshape(-1, 4)
    lat_ms = (got[:, 0] - got[:, 1]) / 1e6
    # Loss from the sequence numbers, apart from a publisher that fell behind its 10 Hz:
    # per vehicle, the seqs between its first and last in the window that never came.
    sent = sum(
        int(seqs.max() - seqs.min() + 1)
        for seqs in (got[got[:, 2] == v, 3] for v in np.unique(got[:, 2]))
    )
    return {
        "vehicles": n,
        "window_s": window_s,
        "received": int(len(got)),
        "delivered_share": len(got) / (n * RATE_HZ * window_s),
        "lost_share": 1.0 - len(np.unique(got[:, 2:4], axis=0)) / max(sent, 1),
        "latency_ms_p50": common.pct(lat_ms, 50),
        "latency_ms_p99": common.pct(lat_ms, 99),
        "latency_ms_max": float(lat_ms.max()) if len(lat_ms) else float("nan"),
        "hub_cpu_us_per_state": (cpu1 - cpu0) * 1e6 / max(len(got), 1),
    }


def role_hub_cmds(kind: str, cfg: MeshConfig, n: int, repeats: int) -> dict:
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command, CommandKind

    ids = set(range(1, n + 1))
    all_ms, errors = [], 0
    with Mesh(cfg) as mesh:
        pres = mesh.presence()
        print("READY", flush=True)

        def raw_once(timeout_s: float = 5.0) -> tuple[int, float]:
            t0 = time.perf_counter()
            got = 0
            for reply in mesh.session.get(
                keys.all_cmds(FLEET),
                payload=bytes(CMD_BYTES),
                timeout=timeout_s,
                target=_zenoh().QueryTarget.ALL,
                consolidation=_zenoh().ConsolidationMode.NONE,
            ):
                got += reply.ok is not None
                if got >= n:
                    break
            return got, time.perf_counter() - t0

        if kind == "raw":
            deadline = time.monotonic() + 90
            while raw_once(2.0)[0] < n and time.monotonic() < deadline:
                time.sleep(0.2)
        elif not pres.wait_for(lambda v, _g: v >= ids, 90.0):
            return {"error": f"only {len(pres.vehicles)} of {n} vehicles present"}
        time.sleep(1.0)
        for _ in range(repeats):
            if kind == "raw":
                got, dt_s = raw_once()
            else:
                t0 = time.perf_counter()
                res = mesh.send_command(
                    Command(CommandKind.LAND, new_nonce(), time.time_ns()),
                    expect=ids,
                    timeout_s=5.0,
                )
                dt_s, got = (
                    time.perf_counter() - t0,
                    sum(o.ack is not None for o in res.outcomes.values()),
                )
            errors += got < n
            all_ms.append(dt_s * 1e3)
            time.sleep(0.05)
    return {
        "vehicles": n,
        "repeats": repeats,
        "incomplete": errors,
        "all_acks_ms_p50": common.pct(all_ms, 50),
        "all_acks_ms_p99": common.pct(all_ms, 99),
    }


def _zenoh():
    import zenoh

    return zenoh


# -- orchestration --------------------------------------------------------------------------------
def _children_for(kids: ChildGroup, what: str, kind: str, port: int, n: int) -> None:
    """Two processes holding the n vehicles (ids 1..n)."""
    half = (n + 1) // 2
    parts = [(1, half), (half + 1, n - half)]
    for first, count in parts:
        if count <= 0:
            continue
        if kind == "fleet-sim":
            p = kids.start(
                "-m",
                "covey_cli",
                "fleet-sim",
                "--vehicles",
                str(count),
                "--first-id",
                str(first),
                "--fleet",
                FLEET,
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--no-see-others",
                "--rate-hz",
                str(RATE_HZ),
            )
        else:
            p = kids.start(
                "-m",
                "bench.mesh",
                "--role",
                what,
                "--kind",
                kind,
                "--port",
                str(port),
                "--first",
                str(first),
                "--count",
                str(count),
            )
        p.wait_for("READY", timeout_s=90)


def run_one(what: str, kind: str, n: int, window_s: float, repeats: int) -> dict:
    port = free_tcp_port()
    with common.children() as kids:
        hub = kids.start(
            "-m",
            "bench.mesh",
            "--role",
            f"hub-{what}",
            "--kind",
            kind,
            "--port",
            str(port),
            "--count",
            str(n),
            "--window-s",
            str(window_s),
            "--repeats",
            str(repeats),
        )
        hub.wait_for("READY", timeout_s=60)
        _children_for(kids, "pub" if what == "states" else "resp", kind, port, n)
        res = json.loads(hub.wait_for("RESULT", timeout_s=180).removeprefix("RESULT"))
    res["kind"] = kind
    return res


def plot(states: list[dict], cmds: list[dict]) -> None:
    plt = common.pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(8, 3.4))
    for kind, color in (("covey", "C0"), ("raw", "C2"), ("raw-batched", "C7"), ("fleet-sim", "C1")):
        rs = sorted(
            (r for r in states if r["kind"] == kind and "latency_ms_p50" in r),
            key=lambda r: r["vehicles"],
        )
        if rs:
            n = [r["vehicles"] for r in rs]
            a1.plot(n, [r["latency_ms_p50"] for r in rs], "o-", color=color, label=f"{kind} p50")
            a1.plot(n, [r["latency_ms_p99"] for r in rs], "o--", color=color, label=f"{kind} p99")
        cs = sorted(
            (r for r in cmds if r["kind"] == kind and "all_acks_ms_p50" in r),
            key=lambda r: r["vehicles"],
        )
        if cs:
            a2.plot(
                [r["vehicles"] for r in cs],
                [r["all_acks_ms_p50"] for r in cs],
                "o-",
                color=color,
                label=f"{kind} p50",
            )
    a1.set(
        xscale="log",
        yscale="log",
        xlabel="vehicles at 10 Hz",
        ylabel="state latency (ms)",
        title="state stamp -> receive",
    )
    a2.set(
        xscale="log", yscale="log", xlabel="vehicles", ylabel="ms", title="broadcast -> all acks"
    )
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    common.save_figure(fig, "mesh")
    plt.close(fig)


def main(quick: bool = False) -> dict:
    window_s, repeats = (3.0, 5) if quick else (8.0, 20)
    state_plan = [
        (k, n) for n in ((10, 100) if quick else (10, 100, 500)) for k in ("covey", "raw")
    ]
    state_plan += (
        [] if quick else [("raw-batched", n) for n in (10, 100, 500)] + [("fleet-sim", 500)]
    )
    cmd_plan = [(k, n) for n in ((10,) if quick else (10, 50)) for k in ("covey", "raw")]
    cmd_plan += [] if quick else [("covey", 500), ("raw", 500), ("fleet-sim", 500)]
    states, cmds = [], []
    for kind, n in state_plan:
        states.append(run_one("states", kind, n, window_s, repeats))
        r = states[-1]
        common.say(
            f"states {kind:9s} n={n:3d}: p50 {r.get('latency_ms_p50', float('nan')):6.2f} ms, p99 {r.get('latency_ms_p99', float('nan')):6.2f} ms, delivered {r.get('delivered_share', 0):.3f}"
        )
    for kind, n in cmd_plan:
        cmds.append(run_one("cmds", kind, n, window_s, repeats))
        r = cmds[-1]
        common.say(
            f"command {kind:9s} n={n:3d}: all acks p50 {r.get('all_acks_ms_p50', float('nan')):6.2f} ms, p99 {r.get('all_acks_ms_p99', float('nan')):6.2f} ms"
        )
    result = {
        "quick": quick,
        "rate_hz": RATE_HZ,
        "state_bytes": STATE_BYTES,
        "states": states,
        "commands": cmds,
        "ratios": ratios(states, cmds),
    }
    plot(states, cmds)
    common.write_json("mesh", result)
    return result


def ratios(states: list[dict], cmds: list[dict]) -> dict:
    """covey / raw for each fleet size: what covey's own layer costs."""
    out = {}
    for rows, key, tag in (
        (states, "latency_ms_p50", "state_p50"),
        (states, "latency_ms_p99", "state_p99"),
        (cmds, "all_acks_ms_p50", "command_p50"),
    ):
        by = {(r["kind"], r["vehicles"]): r.get(key) for r in rows}
        for (kind, n), v in by.items():
            raw = by.get(("raw", n))
            if kind != "raw" and v and raw:
                out[f"{tag}_{kind}_over_raw_n{n}"] = v / raw
    return out


def cli(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--role", default="bench", choices=["bench", "pub", "resp", "hub-states", "hub-cmds"]
    )
    ap.add_argument("--kind", default="covey", choices=["covey", "raw", "raw-batched", "fleet-sim"])
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--connect", default=None, help="every role: a client of this router instead")
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--window-s", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=20)
    a = ap.parse_args(argv)
    kind = "covey" if a.kind == "fleet-sim" else a.kind
    if a.role == "bench":
        main(a.quick)
    elif a.role == "pub":
        role_pub(kind, member(a.port, a.connect), a.first, a.count)
    elif a.role == "resp":
        role_resp(kind, member(a.port, a.connect), a.first, a.count)
    else:
        hub = role_hub_states if a.role == "hub-states" else role_hub_cmds
        cfg = member(a.port, a.connect, hub=True)
        res = hub(kind, cfg, a.count, a.window_s if a.role == "hub-states" else a.repeats)
        print("RESULT " + json.dumps(res), flush=True)
    sys.stdout.flush()


if __name__ == "__main__":
    cli()
