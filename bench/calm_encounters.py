"""Calm ticks against encounters, as the agents fly: the closest approach with calm ticks on
(3.3 Hz while nothing is near, agent/calm.py) and off (`--calm-tick-hz 10`), same scenes.

    python -m bench.calm_encounters [--repeats 2] [--vehicle-model realistic]
    # bench/results/calm_encounters_<model>.json

Real agent loops (`VehicleShell.run`, the real clock, kit/ticks.py's calm schedule), one
`Agent` per vehicle, each on its own Zenoh session to one router, simulated vehicles (ideal,
or realistic: 0.3 s lag, 2.5 m/s^2, gusts, 0.5 m GNSS drift), judged on true positions. The scenes are the ones the calm rule's reaction delay is about
(agent/calm.py): a vehicle holding when another, holding 9 m away, is sent straight through it;
two flying side by side 6.5 m apart (calm) when one turns across the other's path; a
head-on pair from 60 m; `pass_cross`: one flying past another that holds just beyond calm's
reach off its line (calm while it passes, agent/calm.py's closest approach) when the holder is
sent across its path; and `shuffle`: nine vehicles holding on an 8 m grid (ideal vehicles
hold there at the 1 Hz hold tier) each sent at once to another's place, a random
derangement drawn from `--seed` and the run's number, so holders at 1 Hz see neighbours set off
towards them. Each scene is flown with calm ticks on and off (`--calm-tick-hz 10`: no calm or
hold tier), alternating; the closest horizontal distance between any two vehicles is sampled
every 20 ms, and whether every vehicle reached its goal.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import threading
import time
from collections.abc import Callable

import numpy as np

from bench import common
from policy.pointmass import vehicle_model_arg

ALT_M = 10.0
SCENES = ("rest_start", "turn_in", "head_on", "pass_cross", "shuffle")
PASS_NORTH_M = 20.0
"""pass_cross: b holds this far north, `_pass_offset_m` east of a's line, and is sent west
across it when a is 3 m short of abeam: a's closest approach at its velocity is the offset then
(calm since round fourteen's closest-approach rule, agent/calm.py; the gap less |v_rel| tau was
not), and b's turn brings the pair within the filter's berth in 4 s unless the filters act."""
PASS_BEYOND_M = 2.9
"""How far beyond the pair's berth b holds off a's line in pass_cross (ideal: 3.6 + 2.9 =
6.5 m; calm needs the berth + 2.2 m there)."""


def _pass_offset_m(vehicle_model: str) -> float:
    """pass_cross's offset: the pair's berth at the model's reported sigma plus PASS_BEYOND_M."""
    from policy.pointmass import VehicleModel
    from policy.safety import SafetyConfig, pair_radius_m

    sigma = VehicleModel.named(vehicle_model).pos_sigma_m
    r, _ = pair_radius_m(SafetyConfig(), sigma, [sigma])
    return float(np.asarray(r).reshape(-1)[0]) + PASS_BEYOND_M


GRID_M = 8.0
"""The shuffle scene's grid spacing (the demo's)."""
ARRIVED_M = 1.0
"""A vehicle this near its goal at the end of the scene arrived."""
"""The scenes; `--scenes` runs some."""


def _shuffle(rng: np.random.Generator) -> tuple[list, list]:
    """(starts, goals) of the shuffle scene: a 3 x 3 grid, each vehicle to another's place."""
    grid = [(GRID_M * i, GRID_M * j) for i in range(3) for j in range(3)]
    while True:
        perm = rng.permutation(len(grid))
        if (perm != np.arange(len(grid))).all():
            return grid, [grid[k] for k in perm]


def _fly(scene: str, calm_hz: float, vehicle_model: str = "ideal", seed: int = 0) -> dict:
    from agent.agent_cli import sim_config
    from agent.backends.sim import SimBackend
    from agent.failsafe import FailsafeConfig
    from agent.hosts import Agent
    from agent.shell_config import AgentConfig
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import AckResult, Command, Mode
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    goals: list = []
    if scene == "shuffle":
        starts, goals = _shuffle(np.random.default_rng(seed))
    else:
        starts = {
            "rest_start": [(0.0, 0.0), (0.0, 9.0)],
            "turn_in": [(0.0, 0.0), (0.0, 6.5)],
            "head_on": [(0.0, 0.0), (60.0, 0.0)],
            "pass_cross": [(0.0, 0.0), (PASS_NORTH_M, _pass_offset_m(vehicle_model))],
        }[scene]
    port, fleet = free_tcp_port(), f"calm-{scene}"
    stop = threading.Event()

    def cmd(ag: Agent, make: Callable[..., Command], *args: float) -> None:
        ack = ag.handle_command(make(*args, nonce=new_nonce(), stamp_ns=time.time_ns()))
        if ack.result is not AckResult.ACCEPTED:
            raise RuntimeError(f"{scene}: {ack.reason}")

    with (
        Mesh(embedded_router(port, fleet=fleet)) as _hub,
        contextlib.ExitStack() as held,
    ):
        meshes = [held.enter_context(Mesh(embedded_peer(port, fleet=fleet))) for _ in starts]
        agents = []
        for vid, (mesh, ne) in enumerate(zip(meshes, starts, strict=True), start=1):
            cfg = AgentConfig(
                vehicle_id=vid,
                failsafe=FailsafeConfig(require_gcs=False),
                calm_tick_hz=calm_hz,
            )
            sim = sim_config(vehicle_model, start_ned_m=(ne[0], ne[1], 0.0))
            agents.append(
                held.enter_context(Agent(cfg, SimBackend(sim, now_s=time.monotonic()), mesh))
            )
        a, b = agents[:2]
        loops = [threading.Thread(target=ag.run, args=(stop,), daemon=True) for ag in agents]
        try:
            for loop in loops:
                loop.start()
            for ag in agents:
                cmd(ag, Command.takeoff, ALT_M)
            deadline = time.monotonic() + 30.0
            while not all(ag.mode is Mode.HOLDING for ag in agents):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{scene}: never both holding")
                time.sleep(0.05)
            time.sleep(2.0)  # calm by now where the scene is calm
            calm_before = tuple(ag._calm for ag in agents)
            if scene == "shuffle":  # everyone at once to another's place
                for ag, goal in zip(agents, goals, strict=True):
                    cmd(ag, Command.goto_local, goal[0], goal[1], -ALT_M)
                fly_s = 50.0
            elif scene == "rest_start":  # b straight through a, 20 m beyond
                cmd(b, Command.goto_local, 0.0, -20.0, -ALT_M)
                fly_s = 35.0
            elif scene == "turn_in":  # side by side north, then b cuts across a's line
                cmd(a, Command.goto_local, 80.0, 0.0, -ALT_M)
                cmd(b, Command.goto_local, 80.0, 6.5, -ALT_M)
                time.sleep(8.0)
                calm_before = tuple(ag._calm for ag in agents)
                here = b.vehicles.read().pos_m[0]
                cmd(b, Command.goto_local, float(here[0]) + 8.0, -12.0, -ALT_M)
                fly_s = 25.0
            elif scene == "pass_cross":  # a flies past b; b cuts across a's line just ahead
                cmd(a, Command.goto_local, 80.0, 0.0, -ALT_M)
                deadline = time.monotonic() + 40.0
                while a.vehicles.read().pos_m[0][0] < PASS_NORTH_M - 3.0:
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"{scene}: a never came near b")
                    time.sleep(0.01)
                calm_before = tuple(ag._calm for ag in agents)
                cmd(b, Command.goto_local, PASS_NORTH_M, -18.0, -ALT_M)
                fly_s = 25.0
            else:  # head-on
                cmd(a, Command.goto_local, 60.0, 0.0, -ALT_M)
                cmd(b, Command.goto_local, 0.0, 0.0, -ALT_M)
                fly_s = 75.0
            closest = closest_est = np.inf
            arrived = 0
            end = time.monotonic() + fly_s
            fleets = [ag.vehicles.backends[0].fleet for ag in agents]  # type: ignore[attr-defined]
            while time.monotonic() < end:
                closest = min(closest, _closest_pair_m([f.true_pos_m[0] for f in fleets]))
                closest_est = min(closest_est, _closest_pair_m([f.pos_m[0] for f in fleets]))
                time.sleep(0.02)
            if goals:
                last = np.array([f.pos_m[0][:2] for f in fleets])
                arrived = int((np.hypot(*(last - np.array(goals)).T) <= ARRIVED_M).sum())
        finally:
            stop.set()
            for loop in loops:
                loop.join(5.0)
    return {
        "scene": scene,
        "vehicles": len(starts),
        "seed": seed,
        "arrived": arrived if goals else None,
        "vehicle_model": vehicle_model,
        "calm_tick_hz": calm_hz,
        "closest_m": closest,
        "closest_estimated_m": closest_est,
        "calm_before": calm_before,
    }


def _closest_pair_m(pos: list) -> float:
    """The least horizontal distance between any two of the (3,) positions."""
    p = np.array([q[:2] for q in pos])
    d = np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))
    return float(d[np.triu_indices(len(p), 1)].min())


def main(repeats: int = 2, vehicle_model: str = "ideal", scenes=SCENES, seed: int = 0) -> dict:
    runs = []
    for scene in scenes:
        for k in range(repeats):
            for calm_hz in (10.0 / 3, 10.0):
                r = _fly(scene, calm_hz, vehicle_model, seed + k)
                runs.append(r)
                got = "" if r["arrived"] is None else f", {r['arrived']}/{r['vehicles']} arrived"
                common.say(
                    f"{vehicle_model} {scene:10s} calm ticks {'on ' if calm_hz < 10 else 'off'}: "
                    f"closest {r['closest_m']:.2f} m true, {r['closest_estimated_m']:.2f} m "
                    f"estimated{got} (calm before the change: {r['calm_before']})"
                )
    summary = {
        scene: {
            on: statistics.median(
                r["closest_m"]
                for r in runs
                if r["scene"] == scene and (r["calm_tick_hz"] < 10) == (on == "calm_on")
            )
            for on in ("calm_on", "calm_off")
        }
        for scene in scenes
    }
    result = {
        "vehicle_model": vehicle_model,
        "runs": runs,
        "closest_m_median": summary,
        "machine": common.machine(),
    }
    tail = "" if tuple(scenes) == SCENES else "_" + "_".join(scenes)
    common.write_json(f"calm_encounters_{vehicle_model}{tail}", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--vehicle-model", default="ideal", type=vehicle_model_arg)
    ap.add_argument(
        "--scenes", default=",".join(SCENES), help="comma-separated, of " + ", ".join(SCENES)
    )
    ap.add_argument("--seed", type=int, default=0, help="the shuffle's first derangement")
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error("--repeats must be at least 1")
    scenes = tuple(a.scenes.split(","))
    if not scenes or any(x not in SCENES for x in scenes):
        ap.error(f"--scenes {a.scenes!r}: comma-separated, of {', '.join(SCENES)}")
    main(a.repeats, a.vehicle_model, scenes, a.seed)
