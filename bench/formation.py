"""Formations: how long the slot assignment takes, and how a fleet flies a formation change.

    python -m bench.formation [--quick]   # bench/results/formation.{json,png}, docs/bench_formation.png

1. Assignment time (groundstation/formation.py `assign`: minimum sum of squared distances,
   scipy's linear_sum_assignment) for N vehicles at random positions to the N slots of a grid,
   N = 10 .. 1,000.
2. A formation change of 100 simulated vehicles (the fleet-sim code, in-process on injected
   time, a real Zenoh session for its mesh): from their 10 x 10 start grid, airborne, to a
   circle around the grid's centre, one goto each to the slot of the optimal assignment.
   Measured on true positions: time until every vehicle holds within 1 m of its slot, the
   distance flown against the assignment's straight lines, and the closest two vehicles came.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.hosts import Fleet
from agent.shell_config import FleetSimConfig
from bench import common
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode
from comms.session import embedded_router, free_tcp_port
from groundstation.formation import FormationSpec, assign, plan_formation, slots_ned_m

SIZES = (10, 30, 100, 300, 1000)
CRUISE_M_S = 2.0
SEPARATION_M = 3.0
TAKEOFF_ALT_M = 10.0
SETTLE_TOL_M = 1.0
DT_S = 0.1


def assignment_times(sizes, repeats: int) -> list[dict]:
    rng = np.random.default_rng(36)
    rows = []
    for n in sizes:
        side_m = 6.0 * math.sqrt(n) * 3
        pos = np.column_stack([rng.uniform(0, side_m, (n, 2)), -rng.uniform(5, 30, n)])
        slots = slots_ned_m(FormationSpec("grid", 6.0, (side_m / 2, side_m / 2), 20.0), n)
        t = common.time_calls_s(lambda p=pos, s=slots: assign(p, s), repeats, warmup=1)
        rows.append(
            {"vehicles": n, "median_ms": float(np.median(t) * 1e3), "max_ms": float(t.max() * 1e3)}
        )
        common.say(f"assignment {n:>5} vehicles: {rows[-1]['median_ms']:.2f} ms")
    return rows


def _cmd(kind: CommandKind, *params: float) -> Command:
    return Command(kind, new_nonce(), 0, params=tuple(params) + (0.0,) * (3 - len(params)))


def formation_change(n: int, spacing_m: float) -> dict:
    """Fly n vehicles from their start grid (airborne) to a circle; numbers on true positions."""
    clock = [0.0]
    cfg = FleetSimConfig(
        vehicles=n,
        mesh=embedded_router(free_tcp_port(), fleet="benchformation"),
        spacing_m=6.0,
        see_others=False,
        guidance=GuidanceConfig(cruise_speed_m_s=CRUISE_M_S, separation_m=SEPARATION_M),
        failsafe=FailsafeConfig(require_gcs=False, geofence_radius_m=2000.0),
    )
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])

        def tick() -> None:
            clock[0] += DT_S
            fleet.tick(clock[0])

        for i in range(n):
            fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, TAKEOFF_ALT_M))
        while fleet.modes != [Mode.HOLDING] * n and clock[0] < 60:
            tick()
        start = fleet.pos_m.copy()
        centre = tuple(start[:, :2].mean(axis=0))
        spec = FormationSpec("circle", spacing_m, centre, TAKEOFF_ALT_M)
        wall0 = time.perf_counter()
        fp = plan_formation(
            spec, {int(v): tuple(p) for v, p in zip(fleet.ids, start, strict=True)}, SEPARATION_M
        )
        plan_ms = (time.perf_counter() - wall0) * 1e3
        row_of = {int(v): i for i, v in enumerate(fleet.ids)}
        target = np.empty((n, 3))
        for vid, t in zip(fp.vehicle_ids, fp.targets_ned_m, strict=True):
            i = row_of[vid]
            target[i] = t
            fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, *t))
        t0 = clock[0]
        flown = np.zeros(n)
        last = start.copy()
        min_pair_m = math.inf
        tracks = [start[:, :2].copy()]
        settled_s = math.nan
        while clock[0] - t0 < 600:
            tick()
            pos = fleet.pos_m
            flown += np.linalg.norm(pos - last, axis=1)
            last = pos.copy()
            d = np.linalg.norm(pos[:, None] - pos[None], axis=2) + np.eye(n) * 1e9
            min_pair_m = min(min_pair_m, float(d.min()))
            if round((clock[0] - t0) / DT_S) % 10 == 0:
                tracks.append(pos[:, :2].copy())
            near = np.linalg.norm(pos - target, axis=1) <= SETTLE_TOL_M
            if near.all() and fleet.modes == [Mode.HOLDING] * n:
                settled_s = clock[0] - t0
                break
        tracks.append(fleet.pos_m[:, :2].copy())
    straight = np.linalg.norm(target - start, axis=1)
    return {
        "vehicles": n,
        "shape": f"grid 6 m -> circle, chord {spacing_m:g} m (radius {spacing_m / (2 * math.sin(math.pi / n)):.1f} m)",
        "cruise_m_s": CRUISE_M_S,
        "separation_m": SEPARATION_M,
        "plan_ms": plan_ms,
        "settle_s": settled_s,
        "straight_total_m": float(straight.sum()),
        "flown_total_m": float(flown.sum()),
        "extra_distance_pct": float((flown.sum() / straight.sum() - 1) * 100),
        "longest_straight_m": float(straight.max()),
        "ideal_settle_s": float(straight.max() / CRUISE_M_S),
        "min_separation_m": min_pair_m,
        "_tracks": np.array(tracks),
        "_target": target,
    }


def plot(times: list[dict], change: dict) -> None:
    plt = common.pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.6))
    n = [r["vehicles"] for r in times]
    a.loglog(n, [r["median_ms"] for r in times], "o-")
    a.set_xlabel("vehicles = slots")
    a.set_ylabel("assignment time, ms (median)")
    a.set_title("optimal slot assignment (linear_sum_assignment)")
    a.grid(True, which="both", alpha=0.3)
    tr = change["_tracks"]
    for k in range(tr.shape[1]):
        b.plot(tr[:, k, 1], tr[:, k, 0], lw=0.6, color="tab:blue", alpha=0.6)
    b.plot(tr[0, :, 1], tr[0, :, 0], "k.", ms=3, label="start")
    b.plot(
        change["_target"][:, 1],
        change["_target"][:, 0],
        "o",
        mfc="none",
        color="tab:red",
        ms=4,
        label="slot",
    )
    b.set_aspect("equal")
    b.set_xlabel("east, m")
    b.set_ylabel("north, m")
    b.set_title(
        f"{change['vehicles']} vehicles: settled {change['settle_s']:.0f} s, "
        f"+{change['extra_distance_pct']:.1f} % distance, closest {change['min_separation_m']:.1f} m",
        fontsize=9,
    )
    b.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    common.save_figure(fig, "formation")


def main(quick: bool = False) -> dict:
    sizes = SIZES[:3] if quick else SIZES
    times = assignment_times(sizes, repeats=3 if quick else 5)
    n = 30 if quick else 100
    common.say(f"formation change of {n} vehicles")
    change = formation_change(n, spacing_m=4.0 if n >= 60 else 5.0)
    plot(times, change)
    public = {k: v for k, v in change.items() if not k.startswith("_")}
    print(f"assignment {sizes[-1]:,} x {sizes[-1]:,}: {times[-1]['median_ms']:.1f} ms")
    print(
        f"{n} vehicles grid -> circle: settled in {public['settle_s']:.1f} s (straight lines at "
        f"cruise speed: {public['ideal_settle_s']:.1f} s), {public['extra_distance_pct']:+.1f} % "
        f"distance, closest pair {public['min_separation_m']:.2f} m"
    )
    return {"assignment": times, "change": public}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="up to 100 slots, 30 vehicles")
    args = ap.parse_args()
    common.write_json("formation", main(args.quick))
