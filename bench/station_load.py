"""The ground station's load at fleet scale: the fleet feed against every state (issue 15).

    python -m bench.station_load [--quick]      # writes station_load.json

This process hosts the embedded mesh (a router). Children: `processes` `covey fleet-sim`
processes (`block` landed vehicles each, 10 Hz, not listening to each other) and one real
ground station (groundstation/station.py, its viser server up, no browser), which hears the
fleet through the feed (comms/feed.py, the default) or with `every_state`; with `gui=False` the
station child is only its receiving half (a Mesh feeding a FleetModel, no viser, no render
loop), to show what hearing the fleet costs by itself. Over a window after a warm-up the station
child reports its CPU seconds per second (user + system, every thread), its scene updates per
second, the state messages or feed batches and the states its mesh took in per second, and the
vehicles it shows. `station_load()` is one such run, for other benches (bench/scale.py) to call.
"""

from __future__ import annotations

import argparse
import json
import math
import time

from bench import common
from comms.session import embedded_peer, embedded_router, free_tcp_port

FLEET = "benchstation"
SPACING_M = 8.0
"""Start grid spacing of the vehicles (fleet-sim's default); blocks are tiled side by side."""


class _Receiver:
    """The station's receiving half alone: a Mesh feeding a FleetModel, as station.py wires it."""

    def __init__(self, port: int, every_state: bool) -> None:
        from comms.mesh import Mesh
        from groundstation.fleet import FleetModel

        self.mesh = Mesh(embedded_peer(port, fleet=FLEET))
        self.fleet = FleetModel()
        self.update_times_s: list[float] = []  # no render loop
        subscribe = self.mesh.subscribe_states if every_state else self.mesh.subscribe_feed
        subscribe(self.fleet.on_state)
        self.mesh.presence(  # present vehicles stay listed (covey status does the same)
            lambda kind, vid, alive: (
                kind == "vehicle" and self.fleet.on_presence(vid, alive, time.time_ns())
            )
        )

    def __enter__(self) -> _Receiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.mesh.close()


def role_station(port: int, every_state: bool, gui: bool, warm_s: float, window_s: float) -> None:
    """The ground station (or its receiving half); prints READY, then RESULT {json}."""
    from groundstation.station import GcsConfig, GroundStation

    cfg = GcsConfig(mesh=embedded_peer(port, fleet=FLEET), port=0, every_state=every_state)
    with GroundStation(cfg) if gui else _Receiver(port, every_state) as gcs:
        print("READY", flush=True)
        time.sleep(warm_s)
        stats = gcs.mesh.stats

        def now() -> tuple[float, int, int, int]:
            updates = len(gcs.update_times_s)
            return time.process_time(), updates, stats.states_received, stats.feed_batches_received

        before, t0 = now(), time.monotonic()
        time.sleep(window_s)
        after, span_s = now(), time.monotonic() - t0
        shown = len(gcs.fleet.snapshot(time.time_ns(), trails=False).vehicles)
    cpu, updates, states, batches = (a - b for a, b in zip(after, before, strict=True))
    print(
        "RESULT "
        + json.dumps(
            {
                "cpu_s_per_s": cpu / span_s,
                "updates_per_s": updates / span_s if gui else None,
                "states_per_s": states / span_s,
                # The station's mesh takes states one message each, or feed batches.
                "messages_per_s": (states if every_state else batches) / span_s,
                "cpu_us_per_state": cpu / max(states, 1) * 1e6,
                "vehicles_shown": shown,
            }
        ),
        flush=True,
    )


def station_load(
    vehicles: int = 500,
    block: int = 100,
    every_state: bool = False,
    gui: bool = True,
    warm_s: float = 5.0,
    window_s: float = 10.0,
) -> dict:
    """One run: `vehicles` in fleet-sim processes of `block`, and a station child."""
    from comms.mesh import Mesh

    procs = math.ceil(vehicles / block)
    side = math.ceil(math.sqrt(block))
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet=FLEET)), common.children() as kids:
        sims = []
        for k in range(procs):
            n = min(block, vehicles - k * block)
            sims.append(
                kids.start(
                    "-m",
                    "covey_cli",
                    "fleet-sim",
                    "--vehicles",
                    str(n),
                    "--first-id",
                    str(1 + k * block),
                    "--fleet",
                    FLEET,
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                    "--spacing-m",
                    str(SPACING_M),
                    f"--start-ne-m=0,{k * (side + 1) * SPACING_M:g}",
                    "--no-see-others",
                )
            )
        for sim in sims:
            sim.wait_for("READY", 120)
        station = kids.start(
            "-m",
            "bench.station_load",
            "--role",
            "station",
            "--port",
            str(port),
            "--every-state",
            "1" if every_state else "0",
            "--gui",
            "1" if gui else "0",
            "--warm-s",
            str(warm_s),
            "--window-s",
            str(window_s),
        )
        station.wait_for("READY", 120)
        line = station.wait_for("RESULT", warm_s + window_s + 120)
    out = {
        "vehicles": vehicles,
        "processes": procs,
        "every_state": every_state,
        "gui": gui,
        **json.loads(line.split(" ", 1)[1]),
    }
    updates = f"{out['updates_per_s']:.1f} updates/s" if gui else "receiving only"
    common.say(
        f"{vehicles} vehicles in {procs} processes, station "
        f"{'hearing every state' if every_state else 'on the feed'}: "
        f"{out['cpu_s_per_s']:.3f} CPU s/s, {updates}, "
        f"{out['messages_per_s']:.0f} messages/s carrying {out['states_per_s']:.0f} states/s, "
        f"{out['vehicles_shown']} shown"
    )
    return out


def main(quick: bool = False) -> dict:
    vehicles, block = (100, 50) if quick else (500, 100)
    warm_s, window_s = (3.0, 3.0) if quick else (5.0, 10.0)
    runs = [
        station_load(vehicles, block, every_state, gui, warm_s, window_s)
        for gui in (True, False)
        for every_state in (False, True)
    ]
    return {"block": block, "window_s": window_s, "runs": runs}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--role", default="bench", choices=["bench", "station"])
    ap.add_argument("--port", type=int)
    ap.add_argument("--every-state", type=int, default=0)
    ap.add_argument("--gui", type=int, default=1)
    ap.add_argument("--warm-s", type=float, default=5.0)
    ap.add_argument("--window-s", type=float, default=10.0)
    a = ap.parse_args()
    if a.role == "station":
        role_station(a.port, bool(a.every_state), bool(a.gui), a.warm_s, a.window_s)
    else:
        print(common.write_json("station_load", main(a.quick)))
