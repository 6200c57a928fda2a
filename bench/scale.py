"""Per-vehicle load against fleet size at constant density, over several Zenoh routers.

    python -m bench.scale [--quick] [--sizes 100,300,1000]   # writes scale.json and scale.png

For each fleet size n: three router processes (`covey router`, a full mesh on loopback), P
multi-vehicle host processes (the vehicle shell, agent/shell.py, as agent/hosts.py `Fleet`,
n / P vehicles each; P = max(10, n / 100), so at least 10), their vehicle blocks tiled side by
side at one vehicle per SPACING_M² (the density is the same at every size), and a ground
station (the real `GroundStation`, headless: no browser) that is a client of router 1.

Sites, as in the README's multi-site layout: the blocks are split into 3 areas of adjacent blocks
(`layout`), and each host is a Zenoh client of its area's router. Neighbours in the same area
share a router; those across an area's edge are on different routers, and their states cross
two. The neighbour latency is given for all, and for the same-site and cross-site pairs apart.

1. The station sends one TAKEOFF to all and collects every vehicle's ack: ack latency p50/p99.
2. Once the fleet hovers, over a fixed window, per host: states received per second per vehicle
   (what its scoped Zenoh subscriptions delivered, divided by its vehicles), CPU µs per tick per
   vehicle (process user + system time over its ticks), ticks per second, and neighbour state
   latency (the publisher's stamp to the receiver's callback; one clock, one machine). The
   station: updates per second (its render loop), how many vehicles it shows and how fresh,
   and its CPU; the routers' CPU.
A comparison point with unscoped (whole-fleet) subscriptions runs at the smallest size only:
unscoped, every host decodes every state of the fleet (issue 15's "before").

The scoped runs publish with the steady-state rule (comms/state_rate.py, `--steady-state-hz`,
default STEADY_STATE_HZ): a hovering vehicle, whose state its receivers predict, sends 3 states a
second instead of 10. One more run at the largest size sends at the full rate (`steady_hz` 0), as
every vehicle did before the rule, and so does the unscoped comparison.

Open mode (nothing signed): the cost of signatures is measured in bench/trust.py. One 2-core
machine runs every process, routers and station included, so the absolute numbers are this
machine's; the ratios between fleet sizes are the point.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import threading
import time
from dataclasses import dataclass

import numpy as np

from bench import common

FLEET = "benchscale"
SPACING_M = 20.0
"""Grid spacing: one vehicle per 400 m^2 at every fleet size."""
ROUTERS = 3
MIN_HOSTS = 10
MAX_BLOCK = 100
"""At most this many vehicles per host process."""
STEADY_STATE_HZ = 3.0
"""The scoped runs' steady rate (comms/state_rate.py SteadyConfig); 0 = off."""
TAKEOFF_ALT_M = 10.0
LATENCY_SAMPLES = 20_000


# -- child roles --------------------------------------------------------------------------------
def _signal_event(signum: int) -> threading.Event:
    event = threading.Event()
    signal.signal(signum, lambda *_: event.set())
    return event


def role_host(
    connect: str,
    first_id: int,
    vehicles: int,
    start_ne_m: tuple[float, float],
    scoped: bool,
    steady_hz: float,
) -> None:
    """One multi-vehicle host, a client of the router at `connect`. SIGUSR1 starts the
    measurement window (`--window-s`); prints RESULT {json} after it."""
    from agent.hosts import Fleet
    from agent.shell_config import FleetSimConfig
    from comms.mesh import Mesh
    from comms.schema import VehicleState
    from comms.scope import ScopeConfig
    from comms.session import MeshConfig
    from comms.state_rate import SteadyConfig

    measure = _signal_event(signal.SIGUSR1)
    latencies_ms: list[float] = []
    senders: list[int] = []

    class MeasuredFleet(Fleet):
        """The host shell, plus the age of every neighbour state on arrival."""

        def _on_state(self, state: VehicleState, recv_ns: int) -> None:
            if measure.is_set() and len(latencies_ms) < LATENCY_SAMPLES:
                latencies_ms.append((recv_ns - state.stamp_ns) / 1e6)
                senders.append(state.vehicle_id)
            super()._on_state(state, recv_ns)

    cfg = FleetSimConfig(
        vehicles=vehicles,
        first_id=first_id,
        mesh=MeshConfig(fleet=FLEET, mode="client", connect=(connect,)),
        spacing_m=SPACING_M,
        start_ne_m=start_ne_m,
        scope=ScopeConfig(enabled=scoped),
        steady=SteadyConfig(state_hz=steady_hz) if steady_hz > 0 else None,
    )
    stop = threading.Event()
    with Mesh(cfg.mesh) as mesh:
        fleet = MeasuredFleet(cfg, mesh)
        runner = threading.Thread(target=fleet.run, args=(stop,), daemon=True)
        runner.start()
        print("READY", flush=True)
        measure.wait()
        rx0, cpu0, ticks0 = mesh.stats.states_received, time.process_time(), fleet.stats.ticks
        over0 = fleet.stats.overruns
        t0 = time.monotonic()
        time.sleep(ARGS.window_s)
        window_s = time.monotonic() - t0
        rx1, cpu1, ticks1 = mesh.stats.states_received, time.process_time(), fleet.stats.ticks
        airborne = int(np.sum(fleet.pos_m[:, 2] < -0.5 * TAKEOFF_ALT_M))
        stop.set()
        runner.join(timeout=5)
        cells = len(fleet.states.cells) if scoped else None
    ticks = max(1, ticks1 - ticks0)
    result = {
        "rx_per_vehicle_s": (rx1 - rx0) / window_s / vehicles,
        "cpu_us_per_tick_vehicle": (cpu1 - cpu0) / ticks * 1e6 / vehicles,
        "ticks_per_s": (ticks1 - ticks0) / window_s,
        "overruns": fleet.stats.overruns - over0,
        "airborne": airborne,
        "cells": cells,
        "latency_ms": latencies_ms[:2000],
        "latency_senders": senders[:2000],
        "latency_samples": len(latencies_ms),
    }
    print("RESULT " + json.dumps(result), flush=True)


def role_station(connect: str, ids: str) -> None:
    """The ground station, headless, a client of router 1. SIGUSR1: takeoff to all (prints
    ACKS); SIGUSR2: measure the window (prints RESULT)."""
    from comms.commands import OutcomeStatus, new_nonce
    from comms.schema import Command
    from comms.session import MeshConfig, free_tcp_port
    from groundstation.station import GcsConfig, GroundStation

    takeoff = _signal_event(signal.SIGUSR1)
    measure = _signal_event(signal.SIGUSR2)
    first, last = (int(x) for x in ids.split("-"))
    expect = list(range(first, last + 1))
    cfg = GcsConfig(
        mesh=MeshConfig(fleet=FLEET, mode="client", connect=(connect,)),
        port=free_tcp_port(),
        geofence_radius_m=2000.0,
    )
    with GroundStation(cfg) as station:
        renders = [0]
        render_once = station.render_once

        def counted(*a, **kw):
            renders[0] += 1
            return render_once(*a, **kw)

        station.render_once = counted
        print("READY", flush=True)
        takeoff.wait()
        present = station.presence.wait_for(lambda v, _g: set(expect) <= v, 120.0)
        cmd = Command.takeoff(
            TAKEOFF_ALT_M, nonce=new_nonce(), stamp_ns=time.time_ns(), source_id=1
        )
        res = station.mesh.send_command(cmd, expect=expect, timeout_s=30.0)
        lat_s = [o.latency_s for o in res.outcomes.values() if o.status is OutcomeStatus.ACCEPTED]
        print(
            "ACKS "
            + json.dumps(
                {
                    "expected": len(expect),
                    "all_present": present,
                    "present": len(station.presence.vehicles & set(expect)),
                    "accepted": len(lat_s),
                    "latency_ms": [x * 1e3 for x in lat_s],
                }
            ),
            flush=True,
        )
        measure.wait()
        n0, cpu0, t0 = renders[0], time.process_time(), time.monotonic()
        time.sleep(ARGS.window_s)
        window_s = time.monotonic() - t0
        n1, cpu1 = renders[0], time.process_time()
        snap = station.fleet.snapshot(time.time_ns(), trails=False)
        ages = [v.age_s for v in snap.vehicles if math.isfinite(v.age_s)]
        print(
            "RESULT "
            + json.dumps(
                {
                    "updates_per_s": (n1 - n0) / window_s,
                    "cpu_share_of_core": (cpu1 - cpu0) / window_s,
                    "vehicles_shown": len(ages),
                    "age_ms_p50": float(np.median(ages)) * 1e3 if ages else None,
                    "age_ms_p99": float(np.percentile(ages, 99)) * 1e3 if ages else None,
                }
            ),
            flush=True,
        )


# -- the bench ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Block:
    """One host's vehicles: ids first_id.., the block's corner, and the site (router) it is at."""

    first_id: int
    vehicles: int
    start_ne_m: tuple[float, float]
    site: int


def layout(n: int, sites: int = ROUTERS) -> list[Block]:
    """n vehicles in max(MIN_HOSTS, n / MAX_BLOCK) blocks of equal size (+-1), one per host,
    tiled in rows in snake order (block k + 1 is beside block k), and cut into `sites` runs of
    consecutive blocks (block k is at site k * sites // blocks): each site is an area of
    adjacent blocks."""
    hosts = max(MIN_HOSTS, math.ceil(n / MAX_BLOCK))
    sizes = [n // hosts + (1 if k < n % hosts else 0) for k in range(hosts)]
    block_m = SPACING_M * math.ceil(math.sqrt(max(sizes)))
    side = math.ceil(math.sqrt(hosts))
    blocks, first = [], 1
    for k, size in enumerate(sizes):
        row, col = divmod(k, side)
        if row % 2:
            col = side - 1 - col
        blocks.append(Block(first, size, (block_m * row, block_m * col), k * sites // hosts))
        first += size
    return blocks


def site_latencies_ms(blocks: list[Block], rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The neighbour latencies of `rows` (one per block), split into those from a sender at
    the receiver's own site and those from another site."""
    site = {vid: b.site for b in blocks for vid in range(b.first_id, b.first_id + b.vehicles)}
    same, cross = [], []
    for b, r in zip(blocks, rows, strict=True):
        for ms, sender in zip(r["latency_ms"], r["latency_senders"], strict=True):
            if math.isfinite(ms):
                (same if site[sender] == b.site else cross).append(ms)
    return np.array(same), np.array(cross)


def run_fleet(n: int, scoped: bool, window_s: float, hover_wait_s: float, steady_hz: float) -> dict:
    """n vehicles in max(10, n / 100) hosts at three sites (`layout`), one router each, and a
    station; the hosts' steady rate `steady_hz` (0: every state at the full rate)."""
    blocks = layout(n)
    hosts = len(blocks)
    load_1min = os.getloadavg()[0]  # what else ran on the machine as this run began
    with common.children() as kids:
        routers, ports = zip(*common.start_routers(kids, ROUTERS), strict=True)
        procs = []
        for b in blocks:
            procs.append(
                kids.start(
                    "-m",
                    "bench.scale",
                    "--role",
                    "host",
                    "--connect",
                    f"tcp/127.0.0.1:{ports[b.site]}",
                    "--first-id",
                    str(b.first_id),
                    "--vehicles",
                    str(b.vehicles),
                    "--start",
                    f"{b.start_ne_m[0]},{b.start_ne_m[1]}",
                    "--scoped",
                    "1" if scoped else "0",
                    "--window-s",
                    str(window_s),
                    "--steady-state-hz",
                    str(steady_hz),
                )
            )
        station = kids.start(
            "-m",
            "bench.scale",
            "--role",
            "station",
            "--connect",
            f"tcp/127.0.0.1:{ports[0]}",
            "--ids",
            f"1-{n}",
            "--window-s",
            str(window_s),
        )
        for p in (*procs, station):
            p.wait_for("READY", 180)
        time.sleep(3.0)  # presence and subscriptions settle through the routers
        station.send_signal(signal.SIGUSR1)
        acks = json.loads(station.wait_for("ACKS", 120).split(" ", 1)[1])
        common.say(
            f"{n} vehicles: {acks['present']} present, "
            f"{acks['accepted']}/{acks['expected']} takeoff acks"
        )
        time.sleep(hover_wait_s)
        cpu0 = [common.cpu_seconds(r.pid) for r in routers]
        t0 = time.monotonic()
        for p in (*procs, station):
            p.send_signal(signal.SIGUSR2 if p is station else signal.SIGUSR1)
        rows = [json.loads(p.wait_for("RESULT", window_s + 120).split(" ", 1)[1]) for p in procs]
        st = json.loads(station.wait_for("RESULT", window_s + 120).split(" ", 1)[1])
        router_cpu = [
            (common.cpu_seconds(r.pid) - c) / (time.monotonic() - t0)
            for r, c in zip(routers, cpu0, strict=True)
        ]
    lat = np.concatenate([np.array(r["latency_ms"]) for r in rows]) if rows else np.zeros(1)
    lat = lat[np.isfinite(lat)]
    ack_ms = np.array(acks["latency_ms"]) if acks["latency_ms"] else np.full(1, np.nan)
    same, cross = site_latencies_ms(blocks, rows)
    out = {
        "vehicles": n,
        "hosts": hosts,
        "routers": ROUTERS,
        "scoped": scoped,
        "steady_state_hz": steady_hz,
        "rx_per_vehicle_s_mean": float(np.mean([r["rx_per_vehicle_s"] for r in rows])),
        "rx_per_vehicle_s_max": float(np.max([r["rx_per_vehicle_s"] for r in rows])),
        "cpu_us_per_tick_vehicle_mean": float(
            np.mean([r["cpu_us_per_tick_vehicle"] for r in rows])
        ),
        "ticks_per_s_min": float(min(r["ticks_per_s"] for r in rows)),
        "overruns": int(sum(r["overruns"] for r in rows)),
        "airborne": int(sum(r["airborne"] for r in rows)),
        "cells_mean": float(np.mean([r["cells"] for r in rows])) if scoped else None,
        "latency_ms_p50": float(np.percentile(lat, 50)) if lat.size else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if lat.size else None,
        "latency_samples": int(sum(r["latency_samples"] for r in rows)),
        "latency_ms_p99_same_site": float(np.percentile(same, 99)) if same.size else None,
        "latency_ms_p99_cross_site": float(np.percentile(cross, 99)) if cross.size else None,
        "latency_cross_site_share": cross.size / max(1, same.size + cross.size),
        "takeoff_acks": acks["accepted"],
        "takeoff_ack_ms_p50": float(np.nanpercentile(ack_ms, 50)),
        "takeoff_ack_ms_p99": float(np.nanpercentile(ack_ms, 99)),
        "station": st,
        "router_cpu_share_of_core": router_cpu,
        "load_avg_1min_at_start": load_1min,
    }
    common.say(
        f"{n} vehicles {'scoped' if scoped else 'unscoped'}, "
        f"{f'steady {steady_hz:g} Hz' if steady_hz else 'full rate'} "
        f"({hosts} hosts, {ROUTERS} routers): "
        f"{out['rx_per_vehicle_s_mean']:.1f} states/s per vehicle, "
        f"{out['cpu_us_per_tick_vehicle_mean']:.0f} us CPU per tick per vehicle, neighbour "
        f"latency p50 {out['latency_ms_p50']} p99 {out['latency_ms_p99']} ms, station "
        f"{st['updates_per_s']:.1f} updates/s ({st['vehicles_shown']} shown), takeoff acks "
        f"{acks['accepted']}/{n} p50 {out['takeoff_ack_ms_p50']:.0f} p99 "
        f"{out['takeoff_ack_ms_p99']:.0f} ms"
    )
    return out


def figure(runs: list[dict]) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    kinds = (
        (True, True, "o-", "scoped, steady rate"),
        (True, False, "^:", "scoped, full rate"),
        (False, False, "s--", "unscoped (whole fleet), full rate"),
    )
    for scoped, steady, style, label in kinds:
        rs = [r for r in runs if r["scoped"] is scoped and bool(r["steady_state_hz"]) is steady]
        if not rs:
            continue
        n = [r["vehicles"] for r in rs]
        axes[0].plot(n, [r["rx_per_vehicle_s_mean"] for r in rs], style, label=label)
        axes[1].plot(n, [r["cpu_us_per_tick_vehicle_mean"] for r in rs], style, label=label)
        axes[2].plot(n, [r["latency_ms_p99"] for r in rs], style, label=f"{label}, p99")
    axes[0].set(xlabel="vehicles", ylabel="received states/s per vehicle", ylim=(0, None))
    axes[1].set(xlabel="vehicles", ylabel="CPU µs per tick per vehicle", ylim=(0, None))
    axes[2].set(xlabel="vehicles", ylabel="neighbour state latency p99, ms", yscale="log")
    axes[0].legend(fontsize=8)
    fig.suptitle(
        f"hovering fleet, {ROUTERS} sites (a router each), >= {MIN_HOSTS} host processes, one vehicle per "
        f"{SPACING_M**2:.0f} m², one 2-core machine"
    )
    fig.tight_layout()
    common.save_figure(fig, "scale")


def spread(runs: list[dict]) -> dict:
    """The 1,000-vehicle targets over repeated runs of one size: each run's value, the median,
    and how many runs met the target (issue 15: latency p99 <= 20 ms, station >= 10 updates/s
    as printed to one decimal, take-off acks p99 <= 1 s)."""
    out: dict = {
        "runs": len(runs),
        "load_avg_1min_at_start": [r["load_avg_1min_at_start"] for r in runs],
    }
    for key, get, target, ok in (
        ("latency_ms_p99", lambda r: r["latency_ms_p99"], 20.0, lambda v, t: v <= t),
        ("takeoff_ack_ms_p99", lambda r: r["takeoff_ack_ms_p99"], 1000.0, lambda v, t: v <= t),
        (
            "station_updates_per_s",
            lambda r: r["station"]["updates_per_s"],
            10.0,
            lambda v, t: v >= t - 0.05,
        ),
    ):
        values = [float(get(r)) for r in runs]
        out[key] = {
            "values": values,
            "median": float(np.median(values)),
            "target": target,
            "met_in": sum(ok(v, target) for v in values),
        }
    return out


def main(
    quick: bool = False,
    sizes: tuple[int, ...] | None = None,
    steady_hz: float = STEADY_STATE_HZ,
    repeats: int = 1,
) -> dict:
    """`repeats`: how many times the largest scoped size runs (the spread between runs of the
    same code is as large as most changes; docs/scaling.md)."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    sizes = sizes or ((50, 100) if quick else (100, 300, 1000))
    window_s, hover_wait_s = (3.0, 8.0) if quick else (10.0, 10.0)
    runs = [run_fleet(n, True, window_s, hover_wait_s, steady_hz) for n in sizes]
    again = [
        run_fleet(sizes[-1], True, window_s, hover_wait_s, steady_hz) for _ in range(repeats - 1)
    ]
    if steady_hz and not quick:
        runs.append(run_fleet(sizes[-1], True, window_s, hover_wait_s, 0.0))
    runs.append(run_fleet(sizes[0], False, window_s, hover_wait_s, 0.0))
    figure(runs)
    big, small = runs[len(sizes) - 1], runs[0]
    return {
        "spacing_m": SPACING_M,
        "window_s": window_s,
        "runs": runs,
        "largest_repeated": {"vehicles": sizes[-1], **spread([big, *again])},
        "repeat_runs": again,
        "ratio_largest_to_smallest": {
            "rx_per_vehicle_s": big["rx_per_vehicle_s_mean"]
            / max(1e-9, small["rx_per_vehicle_s_mean"]),
            "cpu_us_per_tick_vehicle": big["cpu_us_per_tick_vehicle_mean"]
            / max(1e-9, small["cpu_us_per_tick_vehicle_mean"]),
        },
    }


ARGS = argparse.Namespace(window_s=10.0)

if __name__ == "__main__":
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sizes", default=None, help="fleet sizes, e.g. 100,300,1000")
    ap.add_argument("--role", default="bench", choices=["bench", "host", "station"])
    ap.add_argument("--connect")
    ap.add_argument("--first-id", type=int, default=1)
    ap.add_argument("--vehicles", type=int, default=100)
    ap.add_argument("--ids", default="1-1")
    ap.add_argument("--start", default="0,0")
    ap.add_argument("--scoped", type=int, default=1)
    ap.add_argument("--window-s", type=float, default=10.0)
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run the largest scoped size this many times (medians and ranges in the JSON)",
    )
    ap.add_argument(
        "--steady-state-hz",
        type=float,
        default=STEADY_STATE_HZ,
        help="the scoped runs' steady rate (comms/state_rate.py); 0: full rate only",
    )
    ARGS = ap.parse_args()
    if ARGS.role == "host":
        n_m, e_m = (float(x) for x in ARGS.start.split(","))
        role_host(
            ARGS.connect,
            ARGS.first_id,
            ARGS.vehicles,
            (n_m, e_m),
            bool(ARGS.scoped),
            ARGS.steady_state_hz,
        )
    elif ARGS.role == "station":
        role_station(ARGS.connect, ARGS.ids)
    else:
        chosen = tuple(int(x) for x in ARGS.sizes.split(",")) if ARGS.sizes else None
        if ARGS.repeats < 1:
            ap.error(f"--repeats must be >= 1, got {ARGS.repeats}")
        result = main(ARGS.quick, chosen, ARGS.steady_state_hz, ARGS.repeats)
        print(common.write_json("scale", result))
