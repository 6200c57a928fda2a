"""Formations: how long the slot assignment takes, and how a fleet flies a formation change.

    python -m bench.formation [--quick]   # bench/results/formation.{json,png}, docs/bench_formation.png
    python -m bench.formation --turns [--compare-tree PATH]   # bench/results/formation_turns.*

1. Assignment time (groundstation/formation.py `assign`: minimum sum of squared distances,
   scipy's linear_sum_assignment) for N vehicles at random positions to the N slots of a grid,
   N = 10 .. 1,000.
2. A formation change of 100 simulated vehicles (the fleet-sim code, in-process on injected
   time, a real Zenoh session for its mesh): from their 10 x 10 start grid, airborne, to a
   circle around the grid's centre, one goto each to the slot of the optimal assignment.
   Measured on true positions: time until every vehicle holds within 1 m of its slot, the
   distance flown against the assignment's straight lines, and the closest two vehicles came.
3. `--turns`: eight vehicles in a circle turned by 45-180 degrees (and moved), each keeping its
   slot, ideal and realistic vehicles: their straight lines run along and across the ring past
   vehicles that already hold their slots (policy/sparse.py `still_speed_share`). The time to
   settle, against the straight lines' time, and the closest pair on true positions; with
   `--compare-tree`, the same turns on another checkout, in the same run.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from agent.backends.sim import SimConfig
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
from policy.pointmass import VehicleModel

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


class _Flight:
    """n simulated vehicles of the fleet-sim host (agent.hosts.Fleet, in-process on injected
    time, a real Zenoh session for its mesh), airborne and holding; `fly` sends each its goto
    and measures on true positions."""

    def __init__(self, mesh: Mesh, n: int, model: VehicleModel | None, seed: int) -> None:
        self.clock_s = 0.0
        cfg = FleetSimConfig(
            vehicles=n,
            mesh=mesh.cfg,
            spacing_m=6.0,
            see_others=False,
            guidance=GuidanceConfig(cruise_speed_m_s=CRUISE_M_S, separation_m=SEPARATION_M),
            failsafe=FailsafeConfig(require_gcs=False, geofence_radius_m=2000.0),
            sim=SimConfig(vehicle=model),
        )
        self.fleet = Fleet(cfg, mesh, clock_s=lambda: self.clock_s, rng=np.random.default_rng(seed))
        self.n = n
        for i in range(n):
            self.fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, TAKEOFF_ALT_M))
        while self.fleet.modes != [Mode.HOLDING] * n and self.clock_s < 60:
            self.tick()

    def tick(self) -> None:
        self.clock_s += DT_S
        self.fleet.tick(self.clock_s)

    def fly(self, target: np.ndarray, limit_s: float, track_every: int = 10) -> dict:
        """Each row's goto to target[row] (NED); until every vehicle holds within SETTLE_TOL_M
        of its target (on its estimate, as it judges arrival) or `limit_s`."""
        fleet, n = self.fleet, self.n
        for i in range(n):
            fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, *target[i]))
        start = fleet.sim.true_pos_m.copy()
        t0 = self.clock_s
        flown = np.zeros(n)
        last = start.copy()
        min_pair_m = math.inf
        tracks = [start[:, :2].copy()]
        settled_s = math.nan
        while self.clock_s - t0 < limit_s:
            self.tick()
            true = fleet.sim.true_pos_m
            flown += np.linalg.norm(true - last, axis=1)
            last = true.copy()
            d = np.linalg.norm(true[:, None] - true[None], axis=2) + np.eye(n) * 1e9
            min_pair_m = min(min_pair_m, float(d.min()))
            if round((self.clock_s - t0) / DT_S) % track_every == 0:
                tracks.append(true[:, :2].copy())
            near = np.linalg.norm(fleet.pos_m - target, axis=1) <= SETTLE_TOL_M
            if near.all() and fleet.modes == [Mode.HOLDING] * n:
                settled_s = self.clock_s - t0
                break
        tracks.append(fleet.sim.true_pos_m[:, :2].copy())
        straight = np.linalg.norm(target - start, axis=1)
        return {
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


def _targets(flight: _Flight, fp) -> np.ndarray:
    """Each row's target of a planned formation (groundstation.formation `plan_formation`)."""
    row_of = {int(v): i for i, v in enumerate(flight.fleet.ids)}
    target = np.empty((flight.n, 3))
    for vid, t in zip(fp.vehicle_ids, fp.targets_ned_m, strict=True):
        target[row_of[vid]] = t
    return target


def formation_change(n: int, spacing_m: float) -> dict:
    """Fly n vehicles from their start grid (airborne) to a circle; numbers on true positions."""
    with Mesh(embedded_router(free_tcp_port(), fleet="benchformation")) as mesh:
        flight = _Flight(mesh, n, None, 0)
        start = flight.fleet.pos_m.copy()
        centre = tuple(start[:, :2].mean(axis=0))
        spec = FormationSpec("circle", spacing_m, centre, TAKEOFF_ALT_M)
        wall0 = time.perf_counter()
        fp = plan_formation(
            spec,
            {int(v): tuple(p) for v, p in zip(flight.fleet.ids, start, strict=True)},
            SEPARATION_M,
        )
        plan_ms = (time.perf_counter() - wall0) * 1e3
        flown = flight.fly(_targets(flight, fp), 600.0)
    return {
        "vehicles": n,
        "shape": f"grid 6 m -> circle, chord {spacing_m:g} m (radius {spacing_m / (2 * math.sin(math.pi / n)):.1f} m)",
        "cruise_m_s": CRUISE_M_S,
        "separation_m": SEPARATION_M,
        "plan_ms": plan_ms,
        **flown,
    }


TURNS = tuple((float(a), s) for a in (30, 45, 60, 90, 120, 135, 180) for s in (0.0, 6.0))
"""(heading change in degrees, centre moved north in m) of each turn flown by `formation_turns`."""
QUICK_TURNS = ((45.0, 0.0), (90.0, 6.0), (180.0, 0.0))
TURN_LIMIT_S = 180.0
"""A vehicle that has not settled by then counts as late."""


def formation_turn(model_name: str, turn_deg: float, shift_m: float, seed: int) -> dict:
    """Eight vehicles in a circle turned by turn_deg and moved shift_m north, each keeping its
    slot (as `covey cmd formation` sends a moved formation): the slots' straight lines run
    along and across the ring, past vehicles that already hold theirs. Chord 5 m for ideal
    vehicles, 7 m for realistic ones (their 0.5 m sigmas need a 6.4 m berth)."""
    n = 8
    model = VehicleModel.named(model_name)
    chord_m = 5.0 if model.drift_m == 0 else 7.0
    with Mesh(embedded_router(free_tcp_port(), fleet="benchformationturn")) as mesh:
        flight = _Flight(mesh, n, model if model_name != "ideal" else None, seed)
        start = flight.fleet.pos_m.copy()
        centre = tuple(start[:, :2].mean(axis=0))
        spec = FormationSpec("circle", chord_m, centre, TAKEOFF_ALT_M)
        fp = plan_formation(
            spec,
            {int(v): tuple(p) for v, p in zip(flight.fleet.ids, start, strict=True)},
            SEPARATION_M,
        )
        first = flight.fly(_targets(flight, fp), TURN_LIMIT_S)
        slot_of = {int(v): k for k, v in enumerate(fp.vehicle_ids)}
        moved = FormationSpec(
            "circle", chord_m, (centre[0] + shift_m, centre[1]), TAKEOFF_ALT_M, turn_deg
        )
        slots = slots_ned_m(moved, n)
        target = np.array([slots[slot_of[int(v)]] for v in flight.fleet.ids])
        turned = flight.fly(target, TURN_LIMIT_S)
    public = {k: v for k, v in turned.items() if not k.startswith("_")}
    return {
        "vehicles": model_name,
        "turn_deg": turn_deg,
        "shift_m": shift_m,
        "chord_m": chord_m,
        "seed": seed,
        "first_settle_s": first["settle_s"],
        **public,
        "late": bool(math.isnan(turned["settle_s"])),
    }


def formation_turns(models=("ideal", "realistic"), seeds=(0, 1), turns=TURNS) -> list[dict]:
    rows = []
    for model_name in models:
        for turn_deg, shift_m in turns:
            for seed in seeds if model_name != "ideal" else seeds[:1]:
                r = formation_turn(model_name, turn_deg, shift_m, seed)
                rows.append(r)
                common.say(
                    f"turn {model_name:>9} {turn_deg:>5.0f} deg, moved {shift_m:g} m, seed "
                    f"{seed}: settled {r['settle_s']:.1f} s (straight lines "
                    f"{r['ideal_settle_s']:.1f} s), closest {r['min_separation_m']:.2f} m"
                )
    return rows


def turn_summary(rows: list[dict]) -> dict:
    """Medians over every run, a late one counted at TURN_LIMIT_S (so a lower bound then)."""
    times = [TURN_LIMIT_S if r["late"] else r["settle_s"] for r in rows]
    ratio = [t / r["ideal_settle_s"] for t, r in zip(times, rows, strict=True)]
    return {
        "runs": len(rows),
        "late": sum(r["late"] for r in rows),
        "settle_s_median": float(np.median(times)),
        "settle_s_max": float(max(times)),
        "settle_over_straight_median": float(np.median(ratio)),
        "settle_over_straight_mean": float(np.mean(ratio)),
        "min_separation_m": float(min(r["min_separation_m"] for r in rows)),
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


def _summary_words(sm: dict) -> str:
    return (
        f"{sm['runs'] - sm['late']} of {sm['runs']} settled, median {sm['settle_s_median']:.1f} s "
        f"({sm['settle_over_straight_median']:.2f}x the straight lines, mean "
        f"{sm['settle_over_straight_mean']:.2f}x), longest "
        f"{sm['settle_s_max']:.1f} s, closest {sm['min_separation_m']:.2f} m"
    )


def plot_turns(rows: list[dict], before: list[dict] | None) -> None:
    """Settle time over the straight lines' time, per turn, this tree (and the one compared)."""
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.2))
    labels = [
        f"{r['vehicles'][:4]} {r['turn_deg']:.0f}\u00b0+{r['shift_m']:g}m s{r['seed']}"
        for r in rows
    ]
    x = np.arange(len(rows))

    def ratios(rs):
        return [(TURN_LIMIT_S if r["late"] else r["settle_s"]) / r["ideal_settle_s"] for r in rs]

    w = 0.4 if before else 0.8
    if before:
        ax.bar(
            x - w / 2,
            ratios(before),
            w,
            color="tab:gray",
            label="before (no standing neighbours)",
        )
    ax.bar(x + (w / 2 if before else 0), ratios(rows), w, color="tab:blue", label="this tree")
    ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("settle time / straight lines' time")
    ax.set_yscale("log")
    ax.set_title(
        f"8 vehicles turn a circle keeping their slots (late = {TURN_LIMIT_S:.0f} s)", fontsize=9
    )
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    common.save_figure(fig, "formation_turns")


def turns_main(quick: bool, compare_tree: Path | None) -> dict:
    rows = formation_turns(seeds=(0,) if quick else (0, 1), turns=QUICK_TURNS if quick else TURNS)
    result: dict = {"machine": common.machine(), "limit_s": TURN_LIMIT_S, "runs": rows}
    result["summary"] = {
        m: turn_summary([r for r in rows if r["vehicles"] == m]) for m in ("ideal", "realistic")
    }
    before = None
    if compare_tree is not None:
        common.say(f"the same turns on {compare_tree}")
        before = common.run_in_tree(
            compare_tree, Path(__file__), ["--turns-json", *(["--quick"] if quick else [])]
        )
        result["before"] = {
            "tree": str(compare_tree),
            "runs": before,
            "summary": {
                m: turn_summary([r for r in before if r["vehicles"] == m])
                for m in ("ideal", "realistic")
            },
        }
    plot_turns(rows, before)
    for m, sm in result["summary"].items():
        b = result.get("before", {}).get("summary", {}).get(m)
        print(f"turns, {m}: {_summary_words(sm)}" + (f"; before: {_summary_words(b)}" if b else ""))
    common.write_json("formation_turns", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick", action="store_true", help="up to 100 slots, 30 vehicles; turns: one seed"
    )
    ap.add_argument(
        "--turns",
        action="store_true",
        help="only the turns of a circle of 8 with slots kept (bench/results/formation_turns.json)",
    )
    ap.add_argument(
        "--compare-tree",
        type=Path,
        default=None,
        metavar="PATH",
        help="with --turns: fly the same turns on another checkout (e.g. main before a change)",
    )
    ap.add_argument("--turns-json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.compare_tree is not None and not (args.compare_tree / "agent" / "hosts.py").exists():
        ap.error(f"--compare-tree {args.compare_tree}: no covey checkout there")
    if args.turns_json:
        rows = formation_turns(
            seeds=(0,) if args.quick else (0, 1), turns=QUICK_TURNS if args.quick else TURNS
        )
        print(json.dumps(rows))
    elif args.turns:
        turns_main(args.quick, args.compare_tree)
    else:
        common.write_json("formation", main(args.quick))
