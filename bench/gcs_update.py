"""Ground-station update loop at 100 and 500 vehicles: how long one scene + table update takes.

Drives the fleet model directly (no mesh: this measures the station, not Zenoh) with vehicles
flying circles at 10 Hz in simulated time, with 60 s of trail history already built. One update
is what the station's render loop does each tick: snapshot the model, then inside
`server.atomic()` move every changed scene node (the trail node once all trails were re-read, a tenth per update) and, every tick here,
rebuild the fleet table. A real viser server runs; no browser is connected.

    python -m bench.gcs_update [--vehicles 100,500] [--updates 100]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

from comms.schema import Mode, StateFlag, VehicleState
from groundstation.fleet import NS_PER_S, FleetModel
from groundstation.scene import FleetScene, SceneConfig
from groundstation.tables import fleet_table

RESULTS = Path(__file__).parent / "results" / "gcs_update.json"


@dataclass(frozen=True)
class BenchConfig:
    """What to measure."""

    vehicles: tuple[int, ...] = (100, 500)
    """Fleet sizes to measure."""
    updates: int = 100
    """Timed updates per fleet size (after warm-up)."""
    history_s: float = 60.0
    """Simulated flight before timing, so trails are full."""
    state_hz: float = 10.0
    """Simulated state rate of every vehicle (one state per vehicle per update)."""


def fleet_states(n: int, t_s: float, seq: int) -> list[VehicleState]:
    """n vehicles on concentric circles at 1 m/s, all with goals."""
    out = []
    for i in range(n):
        r = 5.0 + 2.0 * (i % 20)
        a = t_s / r + 2 * math.pi * i / n
        pos = (r * math.cos(a), r * math.sin(a), -5.0 - (i // 20) * 0.5)
        vel = (-math.sin(a), math.cos(a), 0.0)
        out.append(
            VehicleState(
                i + 1,
                seq,
                int(t_s * NS_PER_S),
                pos,
                vel,
                (a + math.pi / 2) % math.pi,
                Mode.GOTO,
                True,
                90.0,
                StateFlag.HAS_GOAL,
                (0.0, 0.0, -5.0),
            )
        )
    return out


def measure(n: int, cfg: BenchConfig) -> dict:
    model = FleetModel()
    for vid in range(1, n + 1):
        model.on_presence(vid, True, 0)
    period_s = 1.0 / cfg.state_hz
    steps = int(cfg.history_s * cfg.state_hz)
    for k in range(steps):
        for s in fleet_states(n, k * period_s, k):
            model.on_state(s, s.stamp_ns)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = FleetScene(server, SceneConfig(geofence_radius_m=60.0))
        times_s, snap_s = [], []
        for j in range(cfg.updates + 5):
            k = steps + j
            now_ns = int(k * period_s * NS_PER_S)
            for s in fleet_states(n, k * period_s, k):
                model.on_state(s, s.stamp_ns)
            t0 = time.perf_counter()
            trails = scene.trail_ids(model.ids())
            snap = model.snapshot(now_ns, trails=trails)
            t1 = time.perf_counter()
            with server.atomic():
                scene.update(snap)
                table = fleet_table(snap)
            t2 = time.perf_counter()
            if j >= 5:  # the first updates create the handles
                times_s.append(t2 - t0)
                snap_s.append(t1 - t0)
        assert table
    finally:
        server.stop()
    t = np.array(times_s)
    return {
        "vehicles": n,
        "updates": len(t),
        "median_ms": round(1e3 * float(np.median(t)), 2),
        "p99_ms": round(1e3 * float(np.percentile(t, 99)), 2),
        "max_ms": round(1e3 * float(t.max()), 2),
        "snapshot_median_ms": round(1e3 * float(np.median(snap_s)), 2),
        "max_rate_hz": round(1.0 / float(np.mean(t)), 1),
        "trail_points_per_vehicle": int(len(model.snapshot(now_ns).vehicles[0].trail_ned_m)),
    }


def main(cfg: BenchConfig) -> dict:
    results = {
        "bench": "gcs_update",
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "python": platform.python_version(),
        "viser": viser.__version__,
        "note": "server side only (no browser connected); one update = snapshot + scene + table",
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "results": [],
    }
    for n in cfg.vehicles:
        r = measure(n, cfg)
        print(
            f"{n:4d} vehicles: median {r['median_ms']:7.2f} ms  p99 {r['p99_ms']:7.2f} ms  "
            f"-> up to {r['max_rate_hz']:6.1f} updates/s  (snapshot {r['snapshot_median_ms']:.2f} ms)",
            flush=True,
        )
        results["results"].append(r)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {RESULTS}")
    return results


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.gcs_update", description=__doc__.splitlines()[0])
    p.add_argument(
        "--vehicles", default="100,500", help="comma-separated fleet sizes (default 100,500)"
    )
    p.add_argument("--updates", type=int, default=100, help="timed updates per size (default 100)")
    args = p.parse_args(argv)
    try:
        sizes = tuple(int(x) for x in args.vehicles.split(","))
    except ValueError:
        p.error(f"--vehicles must be integers like 100,500, got {args.vehicles!r}")
    if not all(1 <= n <= 5000 for n in sizes) or not 1 <= args.updates <= 10_000:
        p.error("fleet sizes must be within 1..5000 and --updates within 1..10000")
    main(BenchConfig(vehicles=sizes, updates=args.updates))
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
