"""CPU of one agent process at 10 Hz with 10 neighbours, and its guidance-tick jitter.

    python -m bench.agent_cpu [--quick]      # writes agent_cpu.json

A real `covey agent` (sim backend) joins a mesh hosted by this process; a second child
publishes 10 neighbours at 10 Hz on a ring 6-14 m around wherever the agent is, at its
altitude and velocity, so that every guidance tick runs the policy and the safety filter on
10 neighbours. The agent takes off and flies a long goto; its CPU time (user + system, all
threads, from /proc/<pid>/stat) is read over a fixed window, first while it sits landed
(the mesh and state publishing alone), then while it flies: once as shipped (the policy decides
at its trained period, the safety filter runs every tick) and once with the policy every tick
(`--decision-period-s 0`). Tick jitter is the spread of the
intervals between the stamps of its published states (one per tick, stamped after guidance).
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from bench import common
from comms.session import embedded_peer, embedded_router, free_tcp_port

FLEET = "benchagent"
NEIGHBOURS = 10
AGENT_ID = 1
TICK_HZ = 10.0


def neighbour_ids(count: int = NEIGHBOURS) -> list[int]:
    return [100 + k for k in range(count)]


def role_neighbours(
    port: int,
    keys_dir: str | None = None,
    count: int = NEIGHBOURS,
    rate_hz: float = TICK_HZ,
    link_tags: bool = True,
    spread: bool = False,
) -> None:
    """Publish `count` vehicles on a ring around the agent's latest state, at `rate_hz`; with
    `keys_dir` (a bench fleet, bench/trust.py) each state is signed with its vehicle's key and,
    with `link_tags`, tagged for the agent, as neighbours that hear it do (trust/links.py).
    `spread`: each vehicle at its own phase, evenly over the period, as vehicles of their own
    tick (every state then reaches the agent alone); else all of a period's at once (they
    reach it in a few batches)."""
    from comms import keys
    from comms.mesh import Mesh
    from comms.schema import Mode, Role, VehicleState
    from trust.auth import load_auth

    signers = {}
    if keys_dir is not None:
        from trust.authority import Authority

        fleet = Authority(keys_dir)
        signers = {
            v: load_auth(str(fleet.member_path(Role.VEHICLE, v))) for v in neighbour_ids(count)
        }
    latest: list[VehicleState | None] = [None]
    tag_for = [AGENT_ID] if link_tags else []
    auth = load_auth(str(Authority(keys_dir).member_path(Role.STATION, 1))) if keys_dir else None
    with Mesh(embedded_peer(port, fleet=FLEET), auth=auth) as mesh:
        mesh.subscribe_states(lambda s, _t: latest.__setitem__(0, s), vehicle_id=AGENT_ID)
        print("READY", flush=True)
        period_s, next_s, seq = 1.0 / rate_hz, time.monotonic(), 0
        while True:
            seq += 1
            me = latest[0]
            c = np.array(me.pos_ned_m) if me is not None else np.array([0.0, 0.0, -10.0])
            v = me.vel_ned_m_s if me is not None else (0.0, 0.0, 0.0)
            for k in range(count):
                if spread:
                    time.sleep(max(0.0, next_s + k * period_s / count - time.monotonic()))
                r_m, th = 6.0 + 8.0 * k / count, 2 * math.pi * k / count + 0.3
                pos = (c[0] + r_m * math.cos(th), c[1] + r_m * math.sin(th), c[2])
                st = VehicleState(
                    100 + k, seq, time.time_ns(), pos, tuple(v), 0.0, mode=Mode.GOTO, armed=True
                )
                if signers:
                    mesh.session.put(
                        keys.state(FLEET, st.vehicle_id, keys.cell_of(pos)),
                        signers[st.vehicle_id].sign_state(st, tag_for).encode(),
                    )
                else:
                    mesh.publish_state(st)
            next_s += period_s
            time.sleep(max(0.0, next_s - time.monotonic()))


class StateLog:
    """Stamps and receive times of the agent's states, as this process sees them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[int, int]] = []
        self.latest = None

    def on_state(self, s, _t: int) -> None:
        now = time.time_ns()
        with self.lock:
            self.rows.append((now, s.stamp_ns))
            self.latest = s

    def wait(self, pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.latest is not None and pred(self.latest):
                return
            time.sleep(0.05)
        raise RuntimeError(f"agent never got to {what}")

    def window(self, t0_ns: int, t1_ns: int) -> np.ndarray:
        with self.lock:
            return np.array(
                [r for r in self.rows if t0_ns <= r[0] < t1_ns], dtype=np.int64
            ).reshape(-1, 2)


def measure(pid: int, log: StateLog, window_s: float) -> dict:
    c0, t0, w0 = common.cpu_seconds(pid), time.time_ns(), time.perf_counter()
    time.sleep(window_s)
    c1, t1, w1 = common.cpu_seconds(pid), time.time_ns(), time.perf_counter()
    rows = log.window(t0, t1)
    period_ms = np.diff(np.sort(rows[:, 1])) / 1e6
    jitter_ms = np.abs(period_ms - 1e3 / TICK_HZ)
    return {
        "window_s": w1 - w0,
        "cpu_share_of_one_core": (c1 - c0) / (w1 - w0),
        "cpu_ms_per_tick": (c1 - c0) * 1e3 / ((w1 - w0) * TICK_HZ),
        "states": int(len(rows)),
        "tick_period_ms_p50": common.pct(period_ms, 50),
        "tick_jitter_ms_p50": common.pct(jitter_ms, 50),
        "tick_jitter_ms_p99": common.pct(jitter_ms, 99),
        "state_latency_ms_p50": common.pct((rows[:, 0] - rows[:, 1]) / 1e6, 50),
    }


def fleet_sim_ticks(quick: bool, vehicles: int = 500) -> dict:
    """Wall time of one `covey fleet-sim` tick for `vehicles` in one process (in-process, with
    a real mesh session and injected time): landed, holding at altitude, flying a goto."""
    from agent.hosts import Fleet
    from agent.shell_config import FleetSimConfig
    from comms.mesh import Mesh
    from comms.schema import Command, CommandKind

    clock = [0.0]
    cfg = FleetSimConfig(
        vehicles=vehicles, mesh=embedded_router(free_tcp_port(), fleet=FLEET + "fs")
    )
    reps = 10 if quick else 30
    out = {"vehicles": vehicles, "budget_ms_at_10hz": 100.0}
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])

        def ticks(n: int) -> list[float]:
            ms = []
            for _ in range(n):
                clock[0] += 0.1
                t0 = time.perf_counter()
                fleet.tick(clock[0])
                ms.append((time.perf_counter() - t0) * 1e3)
            return ms

        def command(kind: CommandKind, params) -> None:
            for i in range(vehicles):
                fleet.handle_command(i, Command(kind, 1, 0, params=params(i)))

        out["landed_tick_ms_p50"] = common.pct(ticks(reps), 50)
        command(CommandKind.TAKEOFF, lambda i: (10.0, 0.0, 0.0))
        ticks(60)  # climb to 10 m at 2 m/s
        out["holding_tick_ms_p50"] = common.pct(ticks(reps), 50)
        command(
            CommandKind.GOTO_LOCAL,
            lambda i: (fleet.pos_m[i, 0] + 60.0, fleet.pos_m[i, 1] + 30.0, -10.0),
        )
        flying = ticks(reps)
        out["goto_tick_ms_p50"], out["goto_tick_ms_p99"] = (
            common.pct(flying, 50),
            common.pct(flying, 99),
        )
        out["in_goto"] = sum(m.name == "GOTO" for m in fleet.modes)
    return out


def agent_flight(
    quick: bool,
    decision_period_s: float | None = None,
    keys_dir: str | None = None,
    neighbours: int = NEIGHBOURS,
    neighbour_hz: float = TICK_HZ,
    while_flying: Callable[[int, float], None] | None = None,
    link_tags: bool = True,
    spread: bool = False,
    agent_args: tuple[str, ...] = (),
) -> dict:
    """One real `covey agent` with 10 neighbours: CPU and tick jitter landed, then flying a goto.
    `decision_period_s` None: the policy's trained period (the default); 0: every tick.
    `keys_dir`: a keyed fleet (bench/trust.py): every state signed and verified.
    `while_flying(pid, window_s)`: called as the flying window starts (a profiler, bench/agent_profile.py).
    `link_tags` False: nobody tags states for anyone (trust/links.py): every one is verified.
    `spread`: the neighbours publish at phases of their own (role_neighbours).
    `agent_args`: more `covey agent` flags."""
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command, Mode, Role
    from trust.auth import load_auth

    window_s = 6.0 if quick else 25.0
    port = free_tcp_port()
    log = StateLog()
    extra = [] if decision_period_s is None else ["--decision-period-s", str(decision_period_s)]
    auth, nb_extra = None, []
    if keys_dir is not None:
        from trust.authority import Authority

        fleet = Authority(keys_dir)
        auth = load_auth(str(fleet.member_path(Role.STATION, 1)))
        extra += ["--key-file", str(fleet.member_path(Role.VEHICLE, AGENT_ID))]
        nb_extra = ["--keys-dir", keys_dir, "--link-tags", str(int(link_tags))]
        extra += ["--link-tags", "32" if link_tags else "0"]
    nb_extra += ["--neighbours", str(neighbours), "--neighbour-hz", str(neighbour_hz)]
    nb_extra += ["--spread"] if spread else []
    with Mesh(embedded_router(port, fleet=FLEET), auth=auth) as mesh, common.children() as kids:
        mesh.subscribe_states(log.on_state, vehicle_id=AGENT_ID)
        nb = kids.start(
            "-m", "bench.agent_cpu", "--role", "neighbours", "--port", str(port), *nb_extra
        )
        nb.wait_for("READY")
        agent = kids.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            str(AGENT_ID),
            "--fleet",
            FLEET,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--no-gcs-failsafe",
            "--geofence-radius-m",
            "0",
            "--tick-hz",
            str(TICK_HZ),
            "--state-hz",
            str(TICK_HZ),
            # landed too: the landed phase measures the mesh and 10 Hz states (bench/idle_agents.py
            # measures idle vehicles at their idle rate), and jitter needs a state per tick
            "--idle-state-hz",
            str(TICK_HZ),
            *extra,
            *agent_args,
        )
        log.wait(lambda s: True, 60, "its first state")
        time.sleep(1.0)
        landed = measure(agent.pid, log, 3.0 if quick else 10.0)
        res = mesh.send_command(
            Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=time.time_ns()),
            expect=(AGENT_ID,),
            timeout_s=5,
        )
        if not res.ok:
            raise RuntimeError(f"takeoff refused: {res.summary()}")
        log.wait(lambda s: s.mode is Mode.HOLDING, 30, "holding at altitude")
        res = mesh.send_command(
            Command.goto_local(5000.0, 0.0, -10.0, nonce=new_nonce(), stamp_ns=time.time_ns()),
            expect=(AGENT_ID,),
            timeout_s=5,
        )
        if not res.ok:
            raise RuntimeError(f"goto refused: {res.summary()}")
        log.wait(lambda s: s.mode is Mode.GOTO, 10, "flying the goto")
        time.sleep(1.0)
        if while_flying is not None:
            threading.Thread(target=while_flying, args=(agent.pid, window_s), daemon=True).start()
        flying = measure(agent.pid, log, window_s)
        still_goto = log.latest.mode is Mode.GOTO
    return {"landed": landed, "flying": flying, "stayed_in_goto": still_goto}


def main(quick: bool = False) -> dict:
    held = agent_flight(quick)
    f = held["flying"]
    common.say(
        f"landed: {100 * held['landed']['cpu_share_of_one_core']:.1f} % of a core; flying with {NEIGHBOURS} "
        f"neighbours: {100 * f['cpu_share_of_one_core']:.1f} % of a core, "
        f"jitter p50 {f['tick_jitter_ms_p50']:.2f} ms p99 {f['tick_jitter_ms_p99']:.2f} ms"
    )
    every = (
        None if quick else agent_flight(quick, decision_period_s=0.0)
    )  # --quick: a smoke run, no comparison
    if every is not None:
        common.say(
            f"policy every tick (--decision-period-s 0): {100 * every['flying']['cpu_share_of_one_core']:.1f} % of a core"
        )
    fs = fleet_sim_ticks(quick)
    common.say(
        f"fleet-sim tick at {fs['vehicles']} vehicles: landed {fs['landed_tick_ms_p50']:.0f} ms, "
        f"holding {fs['holding_tick_ms_p50']:.0f} ms, goto {fs['goto_tick_ms_p50']:.0f} ms (budget 100 ms)"
    )
    result = {
        "quick": quick,
        "tick_hz": TICK_HZ,
        "neighbours": NEIGHBOURS,
        **held,
        "flying_policy_every_tick": every["flying"] if every else None,
        "fleet_sim": fs,
    }
    common.write_json("agent_cpu", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--role", default="bench", choices=["bench", "neighbours"])
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument(
        "--keys-dir", default=None, help="neighbours: sign with this bench fleet's keys"
    )
    ap.add_argument("--neighbours", type=int, default=NEIGHBOURS, help="neighbours: how many")
    ap.add_argument(
        "--link-tags", type=int, default=1, choices=(0, 1), help="neighbours: tag for the agent"
    )
    ap.add_argument(
        "--neighbour-hz", type=float, default=TICK_HZ, help="neighbours: their state rate"
    )
    ap.add_argument("--spread", action="store_true", help="neighbours: each at a phase of its own")
    a = ap.parse_args()
    if a.role == "neighbours":
        role_neighbours(
            a.port, a.keys_dir, a.neighbours, a.neighbour_hz, bool(a.link_tags), a.spread
        )
    else:
        main(a.quick)
