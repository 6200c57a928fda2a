"""The two ways to build the vehicle shell (agent/shell.py), for callers that think in one
vehicle or in a simulated fleet: `Agent` is the shell around one backend (a simulator, PX4 over
MAVSDK, a relay), `Fleet` the shell around the rows of one simulated fleet. Both are the same
`VehicleShell`; these only build its backends and signers, and name row 0 for one vehicle.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from agent.autopilots import Autopilots
from agent.backends.base import VehicleBackend
from agent.backends.sim import SimBackend, SimFleet
from agent.guidance import Guidance
from agent.shell import VehicleShell
from agent.shell_config import ShellConfig
from comms.mesh import Mesh
from comms.schema import Command, CommandAck, Mission, Mode
from policy.runtime import GuidancePolicy
from trust.auth import FleetAuth, fleet_auth_of, host_signers

if TYPE_CHECKING:  # the link emulator is imported only when one is asked for
    from comms.link import LinkEmulator


class Agent(VehicleShell):
    """One vehicle: the shell with one row, around `backend`."""

    def __init__(
        self,
        cfg: ShellConfig,
        backend: VehicleBackend,
        mesh: Mesh,
        *,
        guidance: Guidance | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        link: LinkEmulator | None = None,
    ) -> None:
        if len(cfg.ids) != 1:
            raise ValueError(f"an Agent flies one vehicle, got ids {cfg.ids}")
        super().__init__(
            cfg,
            mesh,
            Autopilots([backend], cfg.assumed_pos_sigma_m),
            [fleet_auth_of(mesh)],
            policy=guidance.policy if guidance is not None else None,
            clock_s=clock_s,
            link=link,
        )
        self.vid = cfg.ids[0]
        self.backend = backend

    @property
    def mode(self) -> Mode:
        return self.core.mode_of(0)

    def handle_command(self, cmd: Command) -> CommandAck:
        return self.command(0, cmd)

    def handle_mission(self, mission: Mission) -> CommandAck:
        return self.mission(0, mission)


class Fleet(VehicleShell):
    """Simulated vehicles: the shell with one row per vehicle around one `SimFleet` (its
    vehicles start on `cfg.starts_ned_m()`). `auths`: each vehicle's own FleetAuth (keyed mode,
    trust.auth.load_vehicle_auths; the mesh's must share their roster); None: open mode."""

    def __init__(
        self,
        cfg: ShellConfig,
        mesh: Mesh,
        *,
        auths: Mapping[int, FleetAuth] | None = None,
        policy: GuidancePolicy | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        rng: np.random.Generator | None = None,
        link: LinkEmulator | None = None,
    ) -> None:
        """`rng` draws the simulated vehicles' gusts and GNSS drift (cfg.sim.vehicle; None:
        fresh entropy); `link`: one vehicle's emulated radio (comms.link), or None."""
        signers = host_signers(cfg.ids, fleet_auth_of(mesh), auths)
        self.sim = SimFleet(cfg.sim, cfg.starts_ned_m(), now_s=clock_s(), rng=rng)
        backends = [SimBackend(fleet=self.sim, index=i) for i in range(len(cfg.ids))]
        super().__init__(
            cfg,
            mesh,
            Autopilots(backends, cfg.assumed_pos_sigma_m),
            signers,
            policy=policy or cfg.guidance.load_policy(),
            clock_s=clock_s,
            link=link,
        )

    # -- what tests and benches read -----------------------------------------------------------
    @property
    def pos_m(self) -> np.ndarray:
        return self.sim.pos_m

    @property
    def armed(self) -> np.ndarray:
        return self.sim.armed

    @property
    def home_m(self) -> np.ndarray:
        return self.core.home_m

    @property
    def _decided_s(self) -> np.ndarray:
        guidance = self.core.guidance
        assert guidance is not None  # simulated vehicles fly velocity setpoints
        return guidance.decided_s

    def handle_command(self, i: int, cmd: Command) -> CommandAck:
        return self.command(i, cmd)

    def handle_mission(self, i: int, mission: Mission) -> CommandAck:
        return self.mission(i, mission)
