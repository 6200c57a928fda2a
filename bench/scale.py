"""Per-vehicle load against fleet size at constant density, scoped states against unscoped.

    python -m bench.scale [--quick]      # writes scale.json and scale.png

Several `fleet-sim` children (FLEET_BLOCK vehicles each, landed, on a SPACING_M grid, their
blocks tiled side by side so that the density is the same at every fleet size) join a mesh
hosted by this process, once with scoped state subscriptions (comms/scope.py) and once with
whole-fleet ones. Per child, over a fixed window after a warm-up: states received per second per
vehicle (what its Zenoh subscriptions delivered, divided by its vehicles) and CPU microseconds
per tick per vehicle (the process's user + system time over its ticks). Not yet here (issue 15):
several routers, 1,000 vehicles, neighbour latency, the station's rate, take-off acks.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time

import numpy as np

from bench import common
from comms.session import embedded_peer, embedded_router, free_tcp_port

FLEET = "benchscale"
FLEET_BLOCK = 25
"""Vehicles per fleet-sim child (a 5 x 5 block)."""
SPACING_M = 20.0
"""Grid spacing: one vehicle per 400 m^2 at every fleet size."""


def role_fleet(
    port: int,
    first_id: int,
    start_ne_m: tuple[float, float],
    scoped: bool,
    warm_s: float,
    window_s: float,
) -> None:
    """One fleet-sim process; prints RESULT {json} after the window."""
    from agent.fleet_sim import Fleet, FleetSimConfig
    from comms.mesh import Mesh
    from comms.scope import ScopeConfig

    cfg = FleetSimConfig(
        vehicles=FLEET_BLOCK,
        first_id=first_id,
        mesh=embedded_peer(port, fleet=FLEET),
        spacing_m=SPACING_M,
        start_ne_m=start_ne_m,
        scope=ScopeConfig(enabled=scoped),
    )
    stop = threading.Event()
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh)
        runner = threading.Thread(target=fleet.run, args=(stop,), daemon=True)
        runner.start()
        print("READY", flush=True)
        time.sleep(warm_s)
        rx0, cpu0, ticks0 = mesh.stats.states_received, time.process_time(), fleet.stats.ticks
        time.sleep(window_s)
        rx1, cpu1, ticks1 = mesh.stats.states_received, time.process_time(), fleet.stats.ticks
        stop.set()
        runner.join(timeout=5)
        cells = len(fleet.states.cells) if scoped else None
    ticks = max(1, ticks1 - ticks0)
    print(
        "RESULT "
        + json.dumps(
            {
                "rx_per_vehicle_s": (rx1 - rx0) / window_s / FLEET_BLOCK,
                "cpu_us_per_tick_vehicle": (cpu1 - cpu0) / ticks * 1e6 / FLEET_BLOCK,
                "ticks_per_s": (ticks1 - ticks0) / window_s,
                "cells": cells,
            }
        ),
        flush=True,
    )


def run_fleet(n: int, scoped: bool, warm_s: float, window_s: float) -> dict:
    """n vehicles in n / FLEET_BLOCK children, blocks tiled on a square."""
    from comms.mesh import Mesh

    procs = n // FLEET_BLOCK
    side = math.ceil(math.sqrt(procs))
    block_m = SPACING_M * math.ceil(math.sqrt(FLEET_BLOCK))
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet=FLEET)), common.Children() as kids:
        ps = []
        for k in range(procs):
            start = (block_m * (k // side), block_m * (k % side))
            ps.append(
                kids.start(
                    "-m",
                    "bench.scale",
                    "--role",
                    "fleet",
                    "--port",
                    str(port),
                    "--first-id",
                    str(1 + k * FLEET_BLOCK),
                    "--start",
                    f"{start[0]},{start[1]}",
                    "--scoped",
                    "1" if scoped else "0",
                    "--warm-s",
                    str(warm_s),
                    "--window-s",
                    str(window_s),
                )
            )
        for p in ps:
            kids.wait_line(p, "READY", 120)
        rows = [json.loads(kids.wait_line(p, "RESULT", warm_s + window_s + 120)) for p in ps]
    rx = [r["rx_per_vehicle_s"] for r in rows]
    cpu = [r["cpu_us_per_tick_vehicle"] for r in rows]
    out = {
        "vehicles": n,
        "processes": procs,
        "scoped": scoped,
        "rx_per_vehicle_s_mean": float(np.mean(rx)),
        "rx_per_vehicle_s_max": float(np.max(rx)),
        "cpu_us_per_tick_vehicle_mean": float(np.mean(cpu)),
        "ticks_per_s_min": float(min(r["ticks_per_s"] for r in rows)),
        "cells_mean": float(np.mean([r["cells"] for r in rows])) if scoped else None,
    }
    common.say(
        f"{n} vehicles {'scoped' if scoped else 'unscoped'}: {out['rx_per_vehicle_s_mean']:.0f} "
        f"states/s per vehicle, {out['cpu_us_per_tick_vehicle_mean']:.0f} us CPU per tick per "
        f"vehicle"
    )
    return out


def figure(runs: list[dict]) -> None:
    plt = common.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for scoped, style in ((True, "o-"), (False, "s--")):
        rs = [r for r in runs if r["scoped"] is scoped]
        label = "scoped (cells within reach)" if scoped else "unscoped (whole fleet)"
        n = [r["vehicles"] for r in rs]
        axes[0].plot(n, [r["rx_per_vehicle_s_mean"] for r in rs], style, label=label)
        axes[1].plot(n, [r["cpu_us_per_tick_vehicle_mean"] for r in rs], style, label=label)
    axes[0].set(xlabel="vehicles", ylabel="received states/s per vehicle")
    axes[1].set(xlabel="vehicles", ylabel="CPU us per tick per vehicle")
    axes[0].legend()
    fig.suptitle(f"fleet-sim, {FLEET_BLOCK} vehicles a process, one per {SPACING_M**2:.0f} m^2")
    fig.tight_layout()
    common.save_figure(fig, "scale")


def main(quick: bool = False) -> dict:
    sizes = (50, 100) if quick else (100, 300)
    warm_s, window_s = (3.0, 3.0) if quick else (5.0, 10.0)
    runs = [run_fleet(n, scoped, warm_s, window_s) for n in sizes for scoped in (True, False)]
    figure(runs)
    return {
        "block": FLEET_BLOCK,
        "spacing_m": SPACING_M,
        "window_s": window_s,
        "runs": runs,
    }


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--role", default="bench", choices=["bench", "fleet"])
    ap.add_argument("--port", type=int)
    ap.add_argument("--first-id", type=int, default=1)
    ap.add_argument("--start", default="0,0")
    ap.add_argument("--scoped", type=int, default=1)
    ap.add_argument("--warm-s", type=float, default=5.0)
    ap.add_argument("--window-s", type=float, default=10.0)
    a = ap.parse_args()
    if a.role == "fleet":
        n_m, e_m = (float(x) for x in a.start.split(","))
        role_fleet(a.port, a.first_id, (n_m, e_m), bool(a.scoped), a.warm_s, a.window_s)
    else:
        result = main(a.quick)
        print(common.write_json("scale", result))
