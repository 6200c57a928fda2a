"""CPU of the multi-vehicle host, `covey agent --ids 1-100`, per vehicle per tick.

    python -m bench.host [--quick]      # writes host.json

A real host process of VEHICLES simulated vehicles (10 x 10 grid, 8 m apart) joins a mesh
hosted by this process, which also plays the ground station (its liveliness token, a subscriber
to every state). Its CPU time (user + system, all threads, /proc/<pid>/stat) is read over a
fixed window while the vehicles sit landed, hold at 10 m, and fly a long goto north side by side
(the policy and the safety filter with their neighbours), once in open mode and once keyed (each
vehicle signs its own states with its own key). A tick is counted from the states this process
received (decoded, not verified): states / vehicles. First, steadier on a busy machine, the
CPU time of the host's tick alone, in this process with injected time.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from bench import common
from comms.session import embedded_router, free_tcp_port

FLEET = "benchhost"
VEHICLES = 100
TICK_HZ = 10.0


class States:
    """How many states reached this process, and the latest mode of each vehicle: decoded, not
    verified (what the host costs is measured, not what checking it costs this process)."""

    def __init__(self) -> None:
        self.count = 0
        self.modes: dict = {}

    def on_sample(self, sample) -> None:
        from comms.schema import VehicleState

        s = VehicleState.decode(sample.payload.to_bytes())
        self.count += 1
        self.modes[s.vehicle_id] = s.mode

    def wait(self, pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if len(self.modes) == VEHICLES and pred(self.modes):
                return
            time.sleep(0.1)
        raise RuntimeError(f"the host never got to {what}")


def window(pid: int, states: States, window_s: float) -> dict:
    c0, n0, w0 = common.cpu_seconds(pid), states.count, time.perf_counter()
    time.sleep(window_s)
    c1, n1, w1 = common.cpu_seconds(pid), states.count, time.perf_counter()
    ticks = max(1.0, (n1 - n0) / VEHICLES)
    return {
        "window_s": w1 - w0,
        "cpu_share_of_one_core": (c1 - c0) / (w1 - w0),
        "ticks": ticks,
        "tick_hz": ticks / (w1 - w0),
        "cpu_ms_per_tick": (c1 - c0) * 1e3 / ticks,
        "cpu_us_per_vehicle_tick": (c1 - c0) * 1e6 / ticks / VEHICLES,
    }


def host_run(quick: bool, keyed: bool) -> dict:
    from comms import keys
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command, Mode, Role
    from trust.auth import load_auth
    from trust.authority import throwaway_fleet
    from trust.heartbeat import HeartbeatPublisher

    window_s = 4.0 if quick else 15.0
    port = free_tcp_port()
    states = States()
    with tempfile.TemporaryDirectory(prefix="covey-bench-host-") as d:
        auth, key_args = None, []
        if keyed:
            authority = throwaway_fleet(d, FLEET, vehicles=range(1, VEHICLES + 1))
            auth = load_auth(str(authority.member_path(Role.STATION, 1)))
            key_args = ["--key-dir", d]
        with (
            Mesh(embedded_router(port, fleet=FLEET), auth=auth) as mesh,
            common.children() as kids,
        ):
            mesh.session.declare_subscriber(keys.all_states(FLEET), states.on_sample)
            mesh.declare_gcs(1)
            HeartbeatPublisher(mesh, 1)  # what the host's station-lost failsafe trusts
            host = kids.start(
                "-m",
                "covey_cli",
                "agent",
                "--ids",
                f"1-{VEHICLES}",
                "--fleet",
                FLEET,
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--geofence-radius-m",
                "0",
                "--tick-hz",
                str(TICK_HZ),
                *key_args,
            )
            host.wait_for("READY", timeout_s=120)
            states.wait(lambda m: True, 60, "its first states")
            time.sleep(1.0)
            out = {"landed": window(host.pid, states, window_s)}

            def send(cmd: Command, what: str) -> None:
                res = mesh.send_command(cmd, expect=range(1, VEHICLES + 1), timeout_s=15)
                if not res.ok:
                    raise RuntimeError(f"{what} refused: {res.summary()[:300]}")

            send(Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=0), "takeoff")
            states.wait(lambda m: all(v is Mode.HOLDING for v in m.values()), 60, "holding")
            time.sleep(1.0)
            out["holding"] = window(host.pid, states, window_s)
            send(Command.goto_local(2000.0, 0.0, -10.0, nonce=new_nonce(), stamp_ns=0), "goto")
            states.wait(lambda m: all(v is Mode.GOTO for v in m.values()), 30, "flying")
            time.sleep(1.0)
            out["flying"] = window(host.pid, states, window_s)
            out["stayed_in_goto"] = sum(v is Mode.GOTO for v in states.modes.values())
    return out


def tick_cpu(quick: bool, keyed: bool) -> dict:
    """CPU microseconds per vehicle per tick of the host's tick alone (physics, core, guidance,
    signing and publishing every state), in this process with injected time: steadier than the
    whole process's on a busy machine."""
    from agent.hosts import Fleet
    from agent.shell_config import FleetSimConfig
    from comms.mesh import Mesh
    from comms.schema import Command, CommandKind
    from trust.auth import load_vehicle_auths
    from trust.authority import throwaway_fleet

    ticks = 20 if quick else 100
    clock = [0.0]
    ids = tuple(range(1, VEHICLES + 1))
    cfg = FleetSimConfig(
        ids=ids, mesh=embedded_router(free_tcp_port(), fleet=FLEET), see_others=False
    )
    with tempfile.TemporaryDirectory(prefix="covey-bench-host-") as d:
        auths = None
        if keyed:
            throwaway_fleet(d, FLEET, vehicles=ids)
            auths = load_vehicle_auths(d, ids, fleet=FLEET)
        with Mesh(cfg.mesh, auth=auths[1] if auths else None) as mesh:
            fleet = Fleet(cfg, mesh, auths=auths, clock_s=lambda: clock[0])

            def run(n: int) -> float:
                c0 = time.process_time()
                for _ in range(n):
                    clock[0] += 1.0 / TICK_HZ
                    fleet.tick(clock[0])
                return (time.process_time() - c0) * 1e6 / n / VEHICLES

            def command(kind: CommandKind, params) -> None:
                for i in range(VEHICLES):
                    fleet.handle_command(i, Command(kind, 1 + i, 0, params=params(i)))

            out = {"landed": run(ticks)}
            command(CommandKind.TAKEOFF, lambda i: (10.0, 0.0, 0.0))
            run(60)  # climb to 10 m at 2 m/s
            out["holding"] = run(ticks)
            command(CommandKind.GOTO_LOCAL, lambda i: (fleet.pos_m[i, 0] + 300, 0.0, -10.0))
            out["flying"] = run(ticks)
    return {f"cpu_us_per_vehicle_tick_{k}": v for k, v in out.items()}


def main(quick: bool = False) -> dict:
    result: dict = {"quick": quick, "vehicles": VEHICLES, "tick_hz": TICK_HZ}
    for mode in ("open", "keyed"):
        t = tick_cpu(quick, keyed=mode == "keyed")
        result[f"{mode}_tick_only"] = t
        common.say(
            f"{mode}, the tick alone (in-process): landed {t['cpu_us_per_vehicle_tick_landed']:.0f}"
            f" us, holding {t['cpu_us_per_vehicle_tick_holding']:.0f} us, flying "
            f"{t['cpu_us_per_vehicle_tick_flying']:.0f} us per vehicle per tick"
        )
    for mode in ("open", "keyed"):
        r = host_run(quick, keyed=mode == "keyed")
        result[mode] = r
        common.say(
            f"{mode}: CPU per vehicle per tick landed {r['landed']['cpu_us_per_vehicle_tick']:.0f} us, "
            f"holding {r['holding']['cpu_us_per_vehicle_tick']:.0f} us, flying "
            f"{r['flying']['cpu_us_per_vehicle_tick']:.0f} us ({VEHICLES} vehicles: "
            f"{100 * r['flying']['cpu_share_of_one_core']:.0f} % of a core flying, "
            f"{r['flying']['tick_hz']:.1f} ticks/s)"
        )
    common.write_json("host", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    main(ap.parse_args().quick)
