"""`covey foxglove`: serve a live fleet to Foxglove over its WebSocket protocol.

    covey foxglove --fleet demo --connect tcp/127.0.0.1:7447 [--port 8765] [--host 127.0.0.1]

then in Foxglove: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765. The channels are
the ones every recording carries (recording/foxglove_channels.py), from the same conversion: the
bridge is a Recorder (same Zenoh taps) whose sink is foxglove-sdk's WebSocket server.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import foxglove

from cli.options import (
    add_mesh_args,
    die,
    finite,
    geo_origin,
    key_env_note,
    mesh_config,
    port,
    refuse,
    stop_on_signals,
)
from comms.geo import GeoOrigin
from comms.session import MeshConfig
from recording.foxglove_channels import FLEET_CHANNELS, Converter, FoxgloveConfig, SchemaSpec
from recording.record import RecordConfig, Recorder

DEFAULT_PORT = 8765


@dataclass(frozen=True)
class BridgeConfig:
    """What `covey foxglove` serves, and where."""

    mesh: MeshConfig = field(default_factory=MeshConfig)
    """How to join the mesh; mesh.fleet is the fleet served."""
    host: str = "127.0.0.1"
    """Address the WebSocket server binds to (loopback by default: the protocol has no auth)."""
    port: int = DEFAULT_PORT
    """TCP port of the WebSocket server; 0 = any free port (see FoxgloveBridge.port)."""
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)
    """How the fleet is drawn (origin for the map, separation ring)."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port {self.port} must be within 0..65535")
        if not self.host:
            raise ValueError("host must not be empty")


class WebSocketSink:
    """Converts what the recorder hears and logs it on foxglove-sdk channels (one per topic).
    The fleet's channels (/tf, /scene, /events, /commands, /acks) are advertised at start; a
    vehicle's when it is first heard."""

    def __init__(self, cfg: BridgeConfig) -> None:
        self._ctx = foxglove.Context()
        self._converter = Converter(cfg.foxglove)
        self._channels: dict[str, foxglove.Channel] = {}
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}
        for topic, spec in FLEET_CHANNELS:
            self._channel(topic, spec)
        self.server: foxglove.WebSocketServer | None = foxglove.start_server(
            name=f"covey {cfg.mesh.fleet}", host=cfg.host, port=cfg.port, context=self._ctx
        )

    def _channel(self, topic: str, spec: SchemaSpec) -> foxglove.Channel:
        ch = self._channels.get(topic)
        if ch is None:
            schema = foxglove.Schema(name=spec.name, encoding=spec.encoding, data=spec.data)
            ch = self._channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding=spec.message_encoding, context=self._ctx
            )
        return ch

    def put(self, topic: str, data: bytes, recv_ns: int) -> None:
        # Zenoh calls back from several threads; the converter keeps per-vehicle state.
        with self._lock:
            for out in self._converter.convert(topic, data, recv_ns):
                self._channel(out.topic, out.schema).log(out.data, log_time=out.log_time_ns)
                self.counts[out.topic] = self.counts.get(out.topic, 0) + 1

    def close(self) -> None:
        server, self.server = self.server, None
        if server is None:
            return
        server.stop()
        with self._lock:
            for ch in self._channels.values():
                ch.close()
            self._channels.clear()


class FoxgloveBridge:
    """The live bridge while open: joins the mesh and serves it. Use it as a context manager."""

    def __init__(self, cfg: BridgeConfig, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.cfg = cfg
        self.sink = WebSocketSink(cfg)
        try:
            self._recorder = Recorder(RecordConfig(mesh=cfg.mesh), clock_ns, sink=self.sink)
        except Exception:
            self.sink.close()
            raise

    @property
    def port(self) -> int:
        server = self.sink.server
        if server is None:
            raise RuntimeError("the Foxglove bridge is closed")
        return server.port

    def __enter__(self) -> FoxgloveBridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._recorder.close()  # closes the sink too


# -- command line ----------------------------------------------------------------------------
def add_foxglove_args(p: argparse.ArgumentParser) -> None:
    """Options for how the fleet is drawn, shared with `covey record`."""
    g = p.add_argument_group("foxglove channels")
    g.add_argument(
        "--origin",
        type=geo_origin,
        default=GeoOrigin(),
        metavar="LAT,LON,ALT",
        help="fleet origin (NED 0,0,0) on WGS-84 for the map; default: covey's",
    )
    g.add_argument(
        "--separation-m",
        type=finite("metres"),
        default=3.0,
        help="the fleet's separation: radius of the ring drawn around each vehicle, and what "
        "the planned routes around the plan's zones are computed for (default 3)",
    )


def foxglove_config(args: argparse.Namespace) -> FoxgloveConfig:
    return FoxgloveConfig(origin=args.origin, separation_m=args.separation_m)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey foxglove",
        description="Serve a live fleet to Foxglove (WebSocket protocol): the same channels as "
        "a recording. In Foxglove: Open connection -> Foxglove WebSocket -> ws://HOST:PORT.",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1; the protocol has no auth)",
    )
    p.add_argument(
        "--port",
        type=port,
        default=DEFAULT_PORT,
        help=f"WebSocket port (default {DEFAULT_PORT}; 0 = any free port)",
    )
    p.add_argument(
        "--duration-s",
        type=finite("seconds"),
        default=None,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    add_foxglove_args(p)
    add_mesh_args(p, key_file=False)
    refuse(p, "--key-file", NO_KEY_REASON, show=True)
    return p


NO_KEY_REASON = (
    "the bridge forwards the mesh's bytes as they are and neither signs nor checks them "
    "(covey gcs --key-file shows only verified vehicles)"
)


def main(cfg: BridgeConfig, stop: threading.Event, duration_s: float | None = None) -> int:
    try:
        bridge = FoxgloveBridge(cfg)
    except Exception as exc:  # noqa: BLE001 - the server or the session could not start
        print(f"covey foxglove: cannot serve on {cfg.host}:{cfg.port}: {exc}", file=sys.stderr)
        return 2
    with bridge:
        print(f"foxglove bridge: ws://{cfg.host}:{bridge.port} fleet {cfg.mesh.fleet}", flush=True)
        stop.wait(duration_s)
    return 0


def cli(argv: list[str]) -> int:
    p = parser()
    args = p.parse_args(argv)
    key_env_note(p, NO_KEY_REASON)
    try:
        cfg = BridgeConfig(
            mesh=mesh_config(args, p),
            host=args.host,
            port=args.port,
            foxglove=foxglove_config(args),
        )
    except ValueError as exc:
        die(p, str(exc))
    with stop_on_signals() as stop:
        return main(cfg, stop, args.duration_s)
