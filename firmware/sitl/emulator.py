"""The emulator's real-time loop: links in, vehicle step, telemetry out.

`Emulator.tick(now_s)` does one round and takes the time as an argument, so a test can run the
whole MAVLink stack on a fake clock; `run()` is the thin real-time shell around it.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from typing import Any

from comms.adsb import covey_icao
from comms.mavlink_udp import UdpLink
from firmware.sitl import streams
from firmware.sitl.commands import Autopilot
from firmware.sitl.config import SitlConfig
from firmware.sitl.onboard import PolicyGuidance, load_c_policy
from firmware.sitl.traffic import TrafficStore
from firmware.sitl.vehicle import Vehicle
from policy.pointmass import VehicleModel

log = logging.getLogger(__name__)

AUTOPILOT_COMPONENT = 1


class Emulator:
    """One emulated PX4: its vehicle, its links and its streams. Use as a context manager."""

    def __init__(self, cfg: SitlConfig, now_s: float = 0.0) -> None:
        self.cfg = cfg
        self.boot_s = now_s
        # covey's own report of this vehicle, echoed back by a relay, is not a neighbour
        self.traffic = TrafficStore(cfg.traffic_timeout_s, own_icao=covey_icao(cfg.vehicle_id))
        guidance = None
        if cfg.onboard:
            guidance = PolicyGuidance(
                load_c_policy(
                    cfg.policy_weights,
                    cfg.separation_m,
                    cfg.policy_speed_m_s,
                    cfg.policy_separation_m,
                    cfg.sparse_rule,
                ),
                self.traffic,
                cfg.home,
                cfg.policy_hz,
            )
        model: VehicleModel | None = VehicleModel.named(cfg.vehicle_model)
        if model == VehicleModel.ideal():
            model = None
        self.vehicle = Vehicle(
            params=cfg.params, healthy=cfg.healthy, guidance=guidance, now_s=now_s, model=model
        )
        onboard = {"CVY_SEP_M": cfg.separation_m} if cfg.onboard else None
        self.autopilot = Autopilot(
            self.vehicle, cfg.home, cfg.vehicle_id, self.traffic, onboard_params=onboard
        )
        self._stack = ExitStack()
        self.links = [
            self._stack.enter_context(UdpLink(url, cfg.vehicle_id, AUTOPILOT_COMPONENT))
            for url in cfg.links
        ]
        self.scheduler = streams.Scheduler(
            {
                "heartbeat": 1.0,
                "sys_status": 2.0,
                "extended_sys_state": 2.0,
                "home": 1.0,
                "gps": 2.0,
                "position": cfg.position_hz,
                "traffic": 2.0,
            }
        )
        self.handle_errors = 0

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _broadcast(self, msgs: list[Any]) -> None:
        for link in self.links:
            for m in msgs:
                link.send(m)

    def tick(self, now_s: float) -> None:
        """Receive and handle everything waiting, advance the physics, send what is due."""
        boot_ms = int((now_s - self.boot_s) * 1000.0) & 0xFFFFFFFF
        self.autopilot.boot_ms = boot_ms
        for link in self.links:
            for msg in link.receive():
                try:
                    replies = self.autopilot.handle(msg, now_s)
                except Exception:  # noqa: BLE001 - one bad message must never stop the autopilot
                    self.handle_errors += 1
                    log.exception("error handling %s", msg.get_type())
                    continue
                # PX4 explains a refusal in a STATUSTEXT; send it before the ack so it is there.
                self._broadcast(self._statustexts())
                for r in replies:
                    link.send(r)
        self.vehicle.step(now_s)
        self._broadcast(self._due(now_s, boot_ms))

    def _due(self, now_s: float, boot_ms: int) -> list[Any]:
        v, home, out = self.vehicle, self.cfg.home, []
        for name in self.scheduler.due(now_s):
            if name == "heartbeat":
                out.append(streams.heartbeat(v))
            elif name == "sys_status":
                out.append(streams.sys_status(v, self.cfg.healthy))
            elif name == "extended_sys_state":
                out.append(streams.extended_sys_state(v))
            elif name == "home":
                out.append(streams.home_position(home, boot_ms))
            elif name == "gps":
                out.append(streams.gps_raw_int(v, home, boot_ms))
            elif name == "position":
                out += [
                    streams.global_position_int(v, home, boot_ms),
                    streams.local_position_ned(v, boot_ms),
                    streams.attitude(v, boot_ms),
                ]
            elif name == "traffic":
                held = self.traffic.fresh(now_s)
                out += [streams.adsb_vehicle(e, now_s) for e in held]
        return out + self._statustexts()

    def _statustexts(self) -> list[Any]:
        events, self.vehicle.events[:] = list(self.vehicle.events), []
        return [streams.statustext(e) for e in events]

    def run(self, stop: threading.Event, clock: Callable[[], float] = time.monotonic) -> None:
        """Tick at `physics_hz` until `stop` is set (or `duration_s` has passed)."""
        period_s = 1.0 / self.cfg.physics_hz
        start_s = clock()
        next_s = start_s
        while not stop.is_set():
            now_s = clock()
            if self.cfg.duration_s is not None and now_s - start_s >= self.cfg.duration_s:
                return
            self.tick(now_s)
            if now_s >= next_s:  # a tick on time, not one woken early by a packet
                next_s = max(next_s + period_s, now_s)
            # Sleep on the sockets, so commands are handled as soon as they arrive.
            select.select(self.links, [], [], max(0.0, next_s - clock()))


def main(cfg: SitlConfig, stop: threading.Event | None = None) -> None:
    """Run one emulated autopilot until `stop` is set (or SIGINT/SIGTERM via the CLI)."""
    stop = stop or threading.Event()
    with Emulator(cfg, now_s=time.monotonic()) as emu:
        log.info("sitl %d up on %s", cfg.vehicle_id, ", ".join(cfg.links))
        emu.run(stop)
