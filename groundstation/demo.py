"""`covey demo`: a simulated fleet and the browser ground station, with no external services.

This process hosts the mesh (an embedded Zenoh router on loopback port 7447, where every tool
connects by default, or a free one if it is busy) and the ground
station; each vehicle is a `covey agent --vehicle sim` child process (kit/procs.py). Every child
runs in its own process group and gets SIGTERM if this process dies (PR_SET_PDEATHSIG), so
neither Ctrl-C, nor SIGTERM, nor a crash of the demo leaves orphans.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cli.options import add_config_flags, config_from_flags, finite, stop_on_signals
from cli.options import port as tcp_port
from comms.mesh import Mesh
from comms.schema import Role
from comms.session import DEFAULT_PORT, embedded_router, free_tcp_port, port_free
from comms.state_rate import MIN_STEADY_STATE_HZ, SteadyConfig
from groundstation.station import GcsConfig, GroundStation
from kit.procs import Child, ChildGroup
from policy.pointmass import vehicle_model_arg
from trust.auth import FleetAuth, load_auth
from trust.authority import Authority


@dataclass(frozen=True)
class DemoConfig:
    """What `covey demo` starts."""

    vehicles: int = 5
    """Number of simulated vehicles (one agent process each)."""
    link: str = "perfect"
    """Emulated radio link of every agent: perfect | xbee | wifi."""
    vehicle_model: str = "ideal"
    """How the simulated vehicles fly: ideal | realistic (covey agent --vehicle-model: lag,
    gusts, GNSS drifting 0.5 m, reported with its sigma)."""
    port: int = 8080
    """Web port of the ground station (the next free one is used if busy)."""
    fleet: str = "covey"
    """Fleet name."""
    mesh_port: int = DEFAULT_PORT
    """Loopback port of the embedded Zenoh router: covey's 7447, where every tool connects by
    default (if it is busy, a free one is used and said); 0 = any free port."""
    spacing_m: float = 6.0
    """Distance between neighbouring start positions on the grid."""
    geofence_radius_m: float = 50.0
    """Geofence of every agent and of the station's drawing."""
    coordinated_return: bool = True
    """A return flies each vehicle home on its own altitude layer and lands them one at a time
    (agent/returning.py's defaults); off: home at its own altitude, landing as it arrives."""
    agent_argv: tuple[str, ...] = (sys.executable, "-m", "covey_cli", "agent")
    """How to start one agent (arguments are appended)."""
    agent_extra: tuple[str, ...] = field(default_factory=tuple)
    """Extra arguments for every agent."""
    agent_mesh_mode: str = "client"
    """Zenoh role of every agent: a client of the demo's router (one link each). As peers they
    would also connect to each other (gossip: N (N - 1) / 2 links, each kept alive four times a
    lease), which on one machine buys nothing and costs 40 idle agents more than all their own
    work (docs/scaling.md, "Idle vehicles")."""
    stop_timeout_s: float = 5.0
    """How long children get to exit after SIGTERM before SIGKILL."""
    steady_state_hz: float = MIN_STEADY_STATE_HZ
    """State rate of an agent in the air while its last state still predicts it (hovering,
    flying straight: `covey agent --steady-state-hz`, comms/state_rate.py); 0: off, every agent
    at its full 10 Hz. A hovering fleet then sends, signs and verifies a third of the states,
    which was most of its CPU (docs/companion.md)."""
    keyed: bool = True
    """Run keyed: a throwaway fleet authority and one key per vehicle and for the station, in a
    temporary directory deleted on exit. False (--open-mode): nothing is authenticated."""

    def __post_init__(self) -> None:
        if self.steady_state_hz:
            SteadyConfig(state_hz=self.steady_state_hz)  # raises with the reason if out of range
        if self.agent_mesh_mode not in AGENT_MESH_MODES:
            raise ValueError(
                f"agent_mesh_mode must be peer or client, got {self.agent_mesh_mode!r}"
            )


def grid_starts(n: int, spacing_m: float) -> list[tuple[float, float]]:
    """n (north, east) start positions on a square grid centred on the origin."""
    cols = max(1, math.ceil(math.sqrt(n)))
    rows = math.ceil(n / cols)
    off_n, off_e = (rows - 1) * spacing_m / 2.0, (cols - 1) * spacing_m / 2.0
    return [((i // cols) * spacing_m - off_n, (i % cols) * spacing_m - off_e) for i in range(n)]


def main(cfg: DemoConfig, stop: threading.Event | None = None) -> int:
    stop = stop or threading.Event()
    mesh_port = cfg.mesh_port or free_tcp_port()
    if not port_free(mesh_port):
        busy, mesh_port = mesh_port, free_tcp_port()
        print(
            f"covey demo: mesh port {busy} is busy; using {mesh_port} instead: give the tools "
            f"--connect tcp/127.0.0.1:{mesh_port}",
            flush=True,
        )
    endpoint = f"tcp/127.0.0.1:{mesh_port}"
    gcs_cfg = GcsConfig(port=cfg.port, geofence_radius_m=cfg.geofence_radius_m, link=cfg.link)
    with contextlib.ExitStack() as stack:
        auth: FleetAuth | None = None

        def no_key_args(_vid: int) -> list[str]:
            return []

        key_args: Callable[[int], list[str]] = no_key_args
        cli_key = ""
        if cfg.keyed:
            keys_dir = Path(
                stack.enter_context(tempfile.TemporaryDirectory(prefix="covey-demo-keys-"))
            )
            authority = Authority.init(keys_dir, cfg.fleet)
            cli_station = gcs_cfg.gcs_id + 1  # for `covey cmd` / `covey status` from a terminal
            paths = authority.add_many(
                [(Role.STATION, gcs_cfg.gcs_id), (Role.STATION, cli_station)]
                + [(Role.VEHICLE, v) for v in range(1, cfg.vehicles + 1)]
            )
            cli_key = f" --key-file {paths[1]}"
            auth = load_auth(str(paths[0]), fleet=cfg.fleet)
            key_args = lambda vid: ["--key-file", str(authority.member_path(Role.VEHICLE, vid))]  # noqa: E731
            print(
                f"covey demo: keyed mode: a throwaway fleet authority signed keys for {cfg.vehicles} "
                f"vehicles and stations {gcs_cfg.gcs_id} (this one) and {cli_station} (for covey cmd) "
                f"in {keys_dir} (deleted on exit)",
                flush=True,
            )
        else:
            print(
                "covey demo: OPEN MODE (--open-mode): commands, states and events are NOT "
                "authenticated; anyone on the mesh can fly these vehicles",
                flush=True,
            )
        return _run(cfg, stop, mesh_port, endpoint, gcs_cfg, auth, key_args, cli_key)


C_CORE_BUILD: tuple[str, ...] = (sys.executable, "-m", "agent.guidance_c")
"""Builds the agents' C guidance core (agent/guidance_c.py; a process: the station does not
import the agent)."""


def c_core_flags(argv: tuple[str, ...] = C_CORE_BUILD, timeout_s: float = 120.0) -> tuple[str, ...]:
    """Build the agents' C guidance core once, before they start, instead of in each of them at
    once: () when it is built (they load it), ("--no-c-core",) when it cannot be, said once
    here (they fly numpy, without each saying so)."""
    child = Child(argv, die_with_parent=True)
    with child:
        try:
            code: int | None = child.wait(timeout_s)
        except subprocess.TimeoutExpired:
            code = None
    said = child.output().strip().splitlines()  # all of it: stopping read it to the end
    if code == 0:
        return ()
    why = said[0] if said else f"{' '.join(argv)} exited with {code}"
    print(f"covey demo: {why}; the agents fly numpy (--no-c-core)", flush=True)
    return ("--no-c-core",)


def _run(
    cfg: DemoConfig,
    stop: threading.Event,
    mesh_port: int,
    endpoint: str,
    gcs_cfg: GcsConfig,
    auth,
    key_args,
    cli_key: str,
) -> int:
    with (
        Mesh(embedded_router(mesh_port, fleet=cfg.fleet), auth=auth) as mesh,
        GroundStation(gcs_cfg, mesh=mesh) as gcs,
        # Each agent in its own process group, so that the terminal's Ctrl-C reaches only the
        # demo, which then stops the agents in order (they land their state machines cleanly);
        # the kernel SIGTERMs them if the demo dies without a chance to (PR_SET_PDEATHSIG).
        ChildGroup(
            output="inherit",
            stderr="inherit",
            die_with_parent=True,
            grace_s=cfg.stop_timeout_s,
        ) as children,
    ):
        no_c = c_core_flags()
        for vid, (n, e) in enumerate(grid_starts(cfg.vehicles, cfg.spacing_m), start=1):
            proc = children.start(
                *[
                    *cfg.agent_argv,
                    "--id",
                    str(vid),
                    "--fleet",
                    cfg.fleet,
                    "--connect",
                    endpoint,
                    "--mesh-mode",
                    cfg.agent_mesh_mode,
                    "--vehicle",
                    "sim",
                    "--link",
                    cfg.link,
                    "--vehicle-model",
                    cfg.vehicle_model,
                    f"--start-ne-m={n:g},{e:g}",
                    "--geofence-radius-m",
                    f"{cfg.geofence_radius_m:g}",
                    *key_args(vid),
                    *(() if cfg.coordinated_return else ("--no-coordinated-return",)),
                    *(
                        ("--steady-state-hz", f"{cfg.steady_state_hz:g}")
                        if cfg.steady_state_hz
                        else ()
                    ),
                    *no_c,
                    *cfg.agent_extra,
                ]
            )
            print(f"covey demo: vehicle {vid} pid {proc.pid} start N {n:g} E {e:g}", flush=True)
        port = gcs.port
        if cfg.port and port != cfg.port:
            print(f"covey demo: web port {cfg.port} is busy; using {port} instead", flush=True)
        print(
            f"covey demo: mesh {endpoint} (covey status --connect {endpoint} --fleet {cfg.fleet}{cli_key})",
            flush=True,
        )
        print(
            "covey demo: fly a vehicle that does not cooperate through the fleet: covey intruder "
            f"--from-ne-m=-40,0 --to-ne-m=40,0 --speed-m-s 2 --alt-m 10 --connect {endpoint} "
            f"--fleet {cfg.fleet}{cli_key}",
            flush=True,
        )
        print(
            f"covey demo: ground station at {gcs.url}  (the token logs you in; Ctrl-C to stop)",
            flush=True,
        )
        reported: set[int] = set()
        while not stop.wait(0.5):
            for proc in children:
                if proc.poll() is not None and proc.pid not in reported:
                    reported.add(proc.pid)
                    print(
                        f"covey demo: agent pid {proc.pid} exited with {proc.returncode}",
                        flush=True,
                    )
    print("covey demo: stopped", flush=True)
    return 0


DEMO_FLAGS = (
    "vehicles",
    "port",
    "fleet",
    "mesh_port",
    "spacing_m",
    "geofence_radius_m",
    "coordinated_return",
    "agent_mesh_mode",
    "steady_state_hz",
)
AGENT_MESH_MODES = ("client", "peer")


def _agent_mesh_mode(text: str) -> str:
    if text not in AGENT_MESH_MODES:
        raise argparse.ArgumentTypeError(f"{text!r}: use {' or '.join(AGENT_MESH_MODES)}")
    return text


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="covey demo", description=__doc__.splitlines()[0])
    add_config_flags(
        p,
        DemoConfig,
        only=DEMO_FLAGS,
        types={
            "port": tcp_port,
            "mesh_port": tcp_port,
            "spacing_m": finite("metres", minimum=1.0, inclusive=True),
            "geofence_radius_m": finite("metres"),
            "agent_mesh_mode": _agent_mesh_mode,
        },
    )
    p.add_argument(
        "--link", choices=("perfect", "xbee", "wifi"), default="perfect", help="emulated radio link"
    )
    p.add_argument(
        "--vehicle-model",
        type=vehicle_model_arg,
        default="ideal",
        metavar="MODEL",
        help="how the simulated vehicles fly: ideal, or realistic (0.3 s lag, 2.5 m/s^2, "
        "0.2 m/s gusts, GNSS drifting 0.5 m), optionally with fields changed "
        "(realistic:drift_m=1.0: policy.pointmass.VehicleModel)",
    )
    p.add_argument(
        "--open-mode",
        action="store_true",
        help="run without keys: nothing authenticated (tests only; default: keyed with "
        "throwaway keys)",
    )
    return p


def cli(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if not 1 <= args.vehicles <= 200:
        p.error(f"--vehicles {args.vehicles} must be within 1..200 (one process each)")
    cfg = config_from_flags(
        DemoConfig,
        args,
        only=DEMO_FLAGS,
        link=args.link,
        keyed=not args.open_mode,
        vehicle_model=args.vehicle_model,
    )
    with stop_on_signals() as stop:
        return main(cfg, stop)
