"""The `Mesh` facade: what agents, the ground station and tools use to talk over Zenoh.

Telemetry is latest-wins pub/sub; commands are request/reply with a timeout and an explicit
ack per vehicle; presence is Zenoh liveliness. Every incoming payload is decoded at this boundary:
a malformed one is counted and reported, never raised into Zenoh's callback thread, so one bad
message cannot kill a process.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from comms import keys
from comms.commands import CommandResult, Outcome, OutcomeStatus
from comms.presence import Presence
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    DecodeError,
    Event,
    Mode,
    VehicleState,
)
from comms.session import MeshConfig, open_session

log = logging.getLogger(__name__)

StateCallback = Callable[[VehicleState, int], None]
"""Called with (state, receive stamp in ns) on a Zenoh thread."""
EventCallback = Callable[[Event, int], None]
CommandHandler = Callable[[Command], CommandAck]


@dataclass
class MeshStats:
    """Counters of what crossed this process's boundary (read them, don't write them)."""

    states_sent: int = 0
    states_received: int = 0
    events_received: int = 0
    commands_served: int = 0
    decode_errors: int = 0
    last_decode_error: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def bump(self, name: str, n: int = 1) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + n)


class Mesh:
    """One process's membership of a covey fleet's mesh. Use it as a context manager."""

    def __init__(
        self,
        cfg: MeshConfig,
        *,
        clock_ns: Callable[[], int] = time.time_ns,
        auth: Any = None,
    ) -> None:
        """`auth` is a comms.auth.CommandAuth (signs and checks commands and acks), or None
        for open mode."""
        self.cfg = cfg
        self.fleet = cfg.fleet
        self.clock_ns = clock_ns
        self.auth = auth
        self.stats = MeshStats()
        self._session: zenoh.Session | None = open_session(cfg)
        self._publishers: dict[int, zenoh.Publisher] = {}
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._error_log_ns = 0

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("mesh is closed")
        return self._session

    def __enter__(self) -> Mesh:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            session, self._session = self._session, None
            entities, self._entities = self._entities, []
            self._publishers.clear()
        if session is None:
            return
        for ent in reversed(entities):
            # Best effort: closing the session below frees whatever failed to undeclare.
            with contextlib.suppress(Exception):
                ent.undeclare()
        session.close()

    def _keep(self, entity: Any) -> Any:
        with self._lock:
            self._entities.append(entity)
        return entity

    def _bad(self, where: str, exc: Exception) -> None:
        self.stats.bump("decode_errors")
        self.stats.last_decode_error = f"{where}: {exc}"
        now = time.monotonic_ns()
        if now - self._error_log_ns > 1_000_000_000:  # at most one log line a second
            self._error_log_ns = now
            log.warning("dropped a malformed message on %s: %s", where, exc)

    # -- states ----------------------------------------------------------------------------
    def publish_state(self, state: VehicleState) -> None:
        payload = state.encode()
        pub = self._publishers.get(state.vehicle_id)
        if pub is None:
            pub = self.session.declare_publisher(
                keys.state(self.fleet, state.vehicle_id),
                congestion_control=zenoh.CongestionControl.DROP,
                express=True,
            )
            self._publishers[state.vehicle_id] = self._keep(pub)
        pub.put(payload)
        self.stats.bump("states_sent")

    def subscribe_states(
        self, callback: StateCallback, vehicle_id: int | None = None, link: Any = None
    ) -> Any:
        """Call `callback(state, recv_ns)` for every valid state. `link` (comms.link) stands
        between the wire and the callback and emulates a radio per sender: it may drop, delay or
        thin states, and calls `link.offer(state, recv_ns, deliver)` instead of the callback."""
        key = keys.all_states(self.fleet) if vehicle_id is None else keys.state(self.fleet, vehicle_id)

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            try:
                state = VehicleState.decode(sample.payload.to_bytes())
                parsed = keys.parse_vehicle_key(str(sample.key_expr))
                if parsed is None or parsed[1] != state.vehicle_id:
                    raise DecodeError(f"state of vehicle {state.vehicle_id} arrived on {sample.key_expr}")
            except DecodeError as exc:
                self._bad(str(sample.key_expr), exc)
                return
            self.stats.bump("states_received")
            if link is None:
                _guarded(callback, state, recv_ns)
            else:
                link.offer(state, recv_ns, lambda s, t: _guarded(callback, s, t))

        return self._keep(self.session.declare_subscriber(key, on_sample))

    # -- events ----------------------------------------------------------------------------
    def publish_event(self, event: Event) -> None:
        self.session.put(keys.event(self.fleet, event.vehicle_id or 1), event.encode())

    def event(self, vehicle_id: int, text: str, **kw: Any) -> None:
        self.publish_event(Event(vehicle_id=vehicle_id, stamp_ns=self.clock_ns(), text=text, **kw))

    def subscribe_events(self, callback: EventCallback) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            try:
                ev = Event.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self._bad(str(sample.key_expr), exc)
                return
            self.stats.bump("events_received")
            _guarded(callback, ev, recv_ns)

        return self._keep(self.session.declare_subscriber(keys.all_events(self.fleet), on_sample))

    # -- presence --------------------------------------------------------------------------
    def declare_vehicle(self, vehicle_id: int) -> zenoh.LivelinessToken:
        """Announce this process as vehicle `vehicle_id` until the token is undeclared."""
        return self._keep(self.session.liveliness().declare_token(keys.alive(self.fleet, vehicle_id)))

    def declare_gcs(self, gcs_id: int) -> zenoh.LivelinessToken:
        return self._keep(self.session.liveliness().declare_token(keys.gcs_alive(self.fleet, gcs_id)))

    def presence(
        self,
        on_change: Callable[[str, int, bool], None] | None = None,
    ) -> Presence:
        """Track which vehicles and ground stations are alive. `on_change(kind, id, alive)` is
        called with kind "vehicle" or "gcs"; a late joiner sees everyone already there."""
        pres = Presence(self.fleet, on_change=on_change, clock_ns=self.clock_ns)
        lv = self.session.liveliness()
        self._keep(lv.declare_subscriber(keys.all_alive(self.fleet), pres.on_sample, history=True))
        self._keep(lv.declare_subscriber(keys.all_gcs_alive(self.fleet), pres.on_sample, history=True))
        return pres

    # -- commands --------------------------------------------------------------------------
    def serve_commands(self, vehicle_id: int, handler: CommandHandler) -> Any:
        """Answer commands for `vehicle_id`; `handler` returns the ack (never raise from it:
        an exception becomes a FAILED ack with the exception text)."""
        reply_key = keys.cmd(self.fleet, vehicle_id)
        ack_key = keys.ack(self.fleet, vehicle_id)

        def ack(nonce: int, result: AckResult, reason: str) -> CommandAck:
            return CommandAck(vehicle_id, nonce, self.clock_ns(), result, reason[:96], Mode.LANDED)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                command = Command.decode(payload)
            except DecodeError as exc:
                self._bad(reply_key, exc)
                answer = ack(0, AckResult.REJECTED, f"malformed command: {exc}")
            else:
                if not command.applies_to(vehicle_id):
                    return
                self.stats.bump("commands_served")
                problem = self.auth.check_command(command, vehicle_id) if self.auth else None
                if problem:
                    answer = ack(command.nonce, AckResult.REJECTED, problem)
                else:
                    try:
                        answer = handler(command)
                    except Exception as exc:  # noqa: BLE001 - a handler bug must not kill the agent
                        log.exception("command handler failed")
                        answer = ack(command.nonce, AckResult.FAILED, f"internal error: {exc}")
            if self.auth is not None:
                answer = self.auth.sign_ack(answer)
            payload = answer.encode()
            try:
                query.reply(reply_key, payload)
            except Exception as exc:  # noqa: BLE001 - the querier may be gone
                log.warning("could not reply to a command: %s", exc)
            try:  # a copy for recorders: replies are seen only by the querier
                self.session.put(ack_key, payload)
            except Exception as exc:  # noqa: BLE001
                log.warning("could not publish the ack copy: %s", exc)

        return self._keep(self.session.declare_queryable(reply_key, on_query))

    def send_command(
        self,
        command: Command,
        *,
        expect: Iterable[int] | None = None,
        timeout_s: float = 2.0,
    ) -> CommandResult:
        """Send one command in ONE query and collect every vehicle's answer.

        `expect`: the vehicles that should answer (default: `command.targets`). A vehicle in it
        that does not answer in time is reported as TIMEOUT. Answers from others are kept too.
        """
        if not 0.0 < timeout_s <= 60.0:
            raise ValueError(f"timeout_s={timeout_s} must be within (0, 60]")
        if self.auth is not None:
            command = self.auth.sign_command(command)
        payload = command.encode()
        expected = set(command.targets if expect is None else expect)
        waiting = set(expected)
        key = (
            keys.cmd(self.fleet, command.targets[0])
            if len(command.targets) == 1
            else keys.all_cmds(self.fleet)
        )
        t0 = time.monotonic()
        outcomes: dict[int, Outcome] = {}
        errors: list[str] = []
        replies = self.session.get(
            key,
            payload=payload,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout_s,
        )
        for reply in replies:
            latency_s = time.monotonic() - t0
            if reply.ok is None:
                errors.append(_err_text(reply))
                continue
            try:
                ack = CommandAck.decode(reply.ok.payload.to_bytes())
            except DecodeError as exc:
                self._bad(str(reply.ok.key_expr), exc)
                errors.append(f"malformed ack from {reply.ok.key_expr}: {exc}")
                continue
            problem = self.auth.check_ack(ack, command) if self.auth else None
            if ack.nonce != command.nonce and ack.nonce != 0:
                problem = f"ack nonce {ack.nonce} does not match command nonce {command.nonce}"
            if problem:
                outcomes[ack.vehicle_id] = Outcome(ack.vehicle_id, OutcomeStatus.ERROR, problem, ack, latency_s)
                continue
            outcomes[ack.vehicle_id] = Outcome.from_ack(ack, latency_s)
            waiting.discard(ack.vehicle_id)
            if expected and not waiting:  # O(1) per ack: a 500-vehicle broadcast stays linear
                break
        elapsed_s = time.monotonic() - t0
        # The query ends early when every reachable queryable has answered: a vehicle missing
        # then is not on the mesh at all; one missing at the deadline is on it but silent.
        why = f"no answer within {timeout_s:g} s" if elapsed_s >= 0.9 * timeout_s else "not reachable on the mesh"
        for vid in sorted(expected - outcomes.keys()):
            outcomes[vid] = Outcome(vid, OutcomeStatus.TIMEOUT, why, None, elapsed_s)
        return CommandResult(command=command, outcomes=outcomes, errors=tuple(errors))


def _err_text(reply: zenoh.Reply) -> str:
    try:
        return reply.err.payload.to_string()
    except Exception:  # noqa: BLE001
        return "error reply"


def _guarded(callback: Callable[..., None], *args: Any) -> None:
    try:
        callback(*args)
    except Exception:  # noqa: BLE001 - a subscriber bug must not kill Zenoh's thread
        log.exception("subscriber callback failed")
