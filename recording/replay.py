"""Replay a recording into a fleet, so that a ground station shows the recorded flight.

States are republished with StateFlag.REPLAY set, events as recorded, at the recorded pace
(scaled by `speed`, with an injected clock and sleep). Commands are never re-sent: the replayer
has no code path that sends a query. Presence is not replayed either (no liveliness tokens), so
nothing can mistake the replay for vehicles that take commands. Guidance traces are for
closed-loop replay (tools/closed_loop.py), which reads the file itself: they are not republished.

Replaying into a fleet where any recorded vehicle id is alive is refused: the live vehicles'
agents would take the replayed states for their neighbours. Name another fleet to watch a replay
beside a live flight.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from comms import keys
from comms.mesh import Mesh
from comms.schema import (
    ActionOutcome,
    DecodeError,
    Event,
    EventMessage,
    StateFlag,
    VehicleState,
    decode_event_message,
)
from comms.session import MeshConfig, expects_answer, unreachable, wait_linked
from recording.record import Recorded, Recording, read_recording

LINK_WAIT_S = 3.0
"""How long a replay waits for a router or peer to answer at its --connect endpoints before it
says that nobody did (MeshUnreachable) instead of replaying into nothing."""


class LiveFleetError(RuntimeError):
    """The target fleet has live vehicles with recorded ids; the message says which."""


@dataclass(frozen=True)
class ReplayConfig:
    """What `covey replay` plays, where and how fast."""

    path: str
    """The MCAP recording."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """How to join the mesh; mesh.fleet is the fleet replayed into."""
    speed: float = 1.0
    """Playback speed: 2 = twice as fast; math.inf = as fast as possible."""
    loop: bool = False
    """Start over at the end, until stopped."""
    start_s: float = 0.0
    """Skip the first start_s seconds of the recording."""
    end_s: float | None = None
    """Stop at this many seconds into the recording; None = the end."""
    presence_wait_s: float = 1.0
    """How long to listen for live vehicles before refusing or starting."""

    def __post_init__(self) -> None:
        if not (self.speed > 0 and not math.isnan(self.speed)):
            raise ValueError(f"speed={self.speed} must be > 0 (inf = as fast as possible)")
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise ValueError(f"start_s={self.start_s} must be finite and >= 0")
        if self.end_s is not None and not (math.isfinite(self.end_s) and self.end_s > self.start_s):
            raise ValueError(f"end_s={self.end_s} must be finite and after start_s={self.start_s}")
        if not 0 <= self.presence_wait_s <= 30:
            raise ValueError(f"presence_wait_s={self.presence_wait_s} must be within 0..30")


@dataclass
class ReplayResult:
    states: int = 0
    events: int = 0
    commands_skipped: int = 0
    """Recorded commands that were (by design) not sent."""
    other_skipped: int = 0
    """Presence records, guidance traces, malformed bytes and unknown keys."""
    loops: int = 0


@dataclass(frozen=True)
class Playable:
    """A recorded message ready to publish: its offset into the recording and the message."""

    offset_ns: int
    message: VehicleState | EventMessage | None
    """None for a recorded command (counted, never sent) or something skipped."""
    kind: str


def prepare(rec: Recording, start_s: float = 0.0, end_s: float | None = None) -> list[Playable]:
    """Decode the recording's window [start_s, end_s) into what the replayer publishes."""
    if not rec.messages:
        return []
    t0 = rec.messages[0].log_time_ns
    lo = t0 + round(start_s * 1e9)
    hi = None if end_s is None else t0 + round(end_s * 1e9)
    out = []
    for m in rec.messages:
        if m.log_time_ns < lo or (hi is not None and m.log_time_ns >= hi):
            continue
        out.append(_playable(m, m.log_time_ns - lo))
    return out


def _playable(m: Recorded, offset_ns: int) -> Playable:
    parsed = keys.parse_vehicle_key(m.topic)
    leaf = parsed[2] if parsed else ("cmd" if m.topic.endswith("/cmd") else "other")
    try:
        if leaf == "state":
            s = VehicleState.decode(m.data)
            return Playable(offset_ns, replace(s, flags=s.flags | StateFlag.REPLAY), "state")
        if leaf == "event":
            return Playable(offset_ns, decode_event_message(m.data), "event")
    except DecodeError:
        return Playable(offset_ns, None, "malformed")
    return Playable(offset_ns, None, leaf)


def recorded_vehicles(items: list[Playable]) -> set[int]:
    return {p.message.vehicle_id for p in items if isinstance(p.message, VehicleState)}


def live_vehicles(mesh: Mesh, wait_s: float) -> set[int]:
    """Vehicle ids with a liveliness token in the mesh's fleet. A session that has just opened
    learns of tokens as declarations arrive, so listen for the whole of wait_s, then also ask."""
    pres = mesh.presence()
    time.sleep(wait_s)
    live = pres.vehicles
    for reply in mesh.session.liveliness().get(
        keys.all_alive(mesh.fleet), timeout=max(wait_s, 0.1)
    ):
        if reply.ok is not None:
            parsed = keys.parse_vehicle_key(str(reply.ok.key_expr))
            if parsed is not None and parsed[0] == mesh.fleet:
                live.add(parsed[1])
    return live


def refuse_live(mesh: Mesh, vehicle_ids: set[int], wait_s: float) -> None:
    """Raise LiveFleetError if any of `vehicle_ids` is alive in the mesh's fleet."""
    live = live_vehicles(mesh, wait_s) & vehicle_ids
    if live:
        raise LiveFleetError(
            f"fleet {mesh.fleet!r} has live vehicles {sorted(live)} that are in this recording; "
            f"replaying would feed them fake neighbours. Replay into another fleet (--fleet NAME)."
        )


def play(
    mesh: Mesh,
    items: list[Playable],
    speed: float = 1.0,
    clock_s: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], object] = time.sleep,
    stop: threading.Event | None = None,
    result: ReplayResult | None = None,
) -> ReplayResult:
    """Publish `items` once at the recorded pace / speed. Never sends a command."""
    result = result or ReplayResult()
    if stop is not None and sleep is time.sleep:
        sleep = stop.wait  # a long gap in the recording must not delay Ctrl-C in the recording must not delay Ctrl-C
    start_s = clock_s()
    for p in items:
        if stop is not None and stop.is_set():
            break
        if math.isfinite(speed):
            delay_s = start_s + p.offset_ns / 1e9 / speed - clock_s()
            if delay_s > 0:
                sleep(delay_s)
        if isinstance(p.message, VehicleState):
            mesh.publish_state(p.message)
            result.states += 1
        elif isinstance(p.message, Event):
            mesh.publish_event(p.message)
            result.events += 1
        elif isinstance(p.message, ActionOutcome):
            mesh.publish_outcome(p.message)
            result.events += 1
        elif p.kind == "cmd":
            result.commands_skipped += 1
        else:
            result.other_skipped += 1
    return result


def replay(
    cfg: ReplayConfig,
    stop: threading.Event | None = None,
    clock_s: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    recording: Recording | None = None,
) -> ReplayResult:
    """Refuse a live fleet, then play the recording (looping if asked) until done or stopped.
    Raises MeshUnreachable when nobody answers at cfg.mesh.connect within LINK_WAIT_S."""
    rec = recording if recording is not None else read_recording(cfg.path)
    items = prepare(rec, cfg.start_s, cfg.end_s)
    if not items:
        raise ValueError(f"{cfg.path}: nothing to replay in [{cfg.start_s}, {cfg.end_s}) s")
    result = ReplayResult()
    with Mesh(cfg.mesh, stop=stop, wait_s=LINK_WAIT_S) as mesh:
        if expects_answer(cfg.mesh) and not wait_linked(mesh.session, LINK_WAIT_S, stop):
            raise unreachable(cfg.mesh, LINK_WAIT_S)  # nobody to replay into: nothing sent
        refuse_live(mesh, recorded_vehicles(items), cfg.presence_wait_s)
        while True:
            play(mesh, items, cfg.speed, clock_s, sleep, stop, result)
            result.loops += 1
            if not cfg.loop or (stop is not None and stop.is_set()):
                return result
