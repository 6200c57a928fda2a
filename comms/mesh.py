"""The `Mesh` facade: what agents, the ground station and tools use to talk over Zenoh.

Telemetry is latest-wins pub/sub, and every process also sends its vehicles' latest states as a
bounded-rate feed for ground stations (comms/feed.py); commands are request/reply with a timeout
and an explicit ack per vehicle; presence is Zenoh liveliness. Every incoming payload is decoded
at this boundary: a malformed one is counted and reported, never raised into Zenoh's callback
thread, so one bad message cannot kill a process.

Keyed mode (`auth`, trust/auth.py): every state, event, command and ack this process sends is
signed with its own key; every state and event it receives passes a comms/gate.py Gate first
(unsigned, forged, stale, replayed and out-of-order ones are dropped and counted); the roster is
followed by trust/roster_sync.py (newer ones applied at once, cheapest checks first; pulls at
start, on every new link and periodically; members that are behind answered).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from comms import keys
from comms.arrival import ArrivalEstimate, estimated_ns
from comms.commands import CommandResult, Outcome, OutcomeStatus
from comms.doc_sync import DocSync, RosterSyncConfig
from comms.doc_sync import publish as publish_roster
from comms.feed import FeedBuffer
from comms.gate import Gate, GateConfig, Refusal, Summaries
from comms.heard import Heard, hear_all
from comms.heard import where as heard_at
from comms.member import FleetKeyError, MemberAuth, StateLink, command_digest
from comms.presence import Presence
from comms.relay import RELAY_SILENT_S, CellRelay, MisplacedState, RelayConfig, decode_placed
from comms.schema import (
    AckResult,
    ActionOutcome,
    Command,
    CommandAck,
    DecodeError,
    Event,
    FeedBatch,
    GuidanceTrace,
    Mission,
    Mode,
    MsgType,
    RelayBatch,
    Roster,
    RosterHead,
    VehicleState,
    decode_event_message,
)
from comms.session import MeshConfig, open_session

log = logging.getLogger(__name__)

StateCallback = Callable[[VehicleState, int], None]
"""Called with (state, receive stamp in ns) on a Zenoh thread."""
Admit = Callable[[VehicleState, int, tuple], bool]
"""A subscription's checks and delivery of one decoded state (Mesh._admitters): (state, receive
stamp in ns, extra callback arguments) -> whether it went on."""
AdmitHeard = Callable[[Heard, int], bool]
"""The same for a state heard by a polled subscription (comms/heard.py), decoded only if the
gate's checks of its head pass: (heard, receive stamp in ns) -> whether it went on."""
FeedCallback = Callable[[VehicleState, int, int], None]
"""Called with (state, receive stamp in ns, its entry number in its feed) on a Zenoh thread."""
EventCallback = Callable[[Event, int], None]
OutcomeCallback = Callable[[ActionOutcome, int], None]
CommandHandler = Callable[[Command], CommandAck]
MissionHandler = Callable[[Mission], CommandAck]
"""Answers a mission upload that passed the command checks (agent/mission.py loads it)."""
RefusedCallback = Callable[[int, str, int], None]
"""Called with (claimed vehicle id, refusal cause, receive stamp in ns) for a refused state."""

_SIGNED_BYTES = VehicleState._FMT.size
"""A state's bytes that its signature and link tags cover: `VehicleState.signed_bytes` of a
state its payload decodes to is the payload's first this many bytes."""


def _newest_first(heard: Heard) -> int:
    """The order of one vehicle's polled states that are all plausible (`_state_batch_handler`)."""
    return -heard.stamp_ns


def _plausible_newest_first(late_ns: int, heard: Heard) -> tuple[bool, int]:
    """The order of one vehicle's polled states, those stamped after `late_ns` last."""
    return heard.stamp_ns > late_ns, -heard.stamp_ns


def _rising(states: list[Heard]) -> bool:
    """Whether `states` are stamped strictly later one after the other (then, all plausible,
    `_newest_first` orders them exactly backwards: no two stamps tie)."""
    prev_ns = -1
    for state in states:
        if state.stamp_ns <= prev_ns:
            return False
        prev_ns = state.stamp_ns
    return True


@dataclass
class MeshStats:
    """Counters of what crossed this process's boundary (read them, don't write them)."""

    states_sent: int = 0
    states_received: int = 0
    """States that passed every check, from state keys and feed entries alike."""
    feed_batches_sent: int = 0
    feed_batches_received: int = 0
    """Feed batches that decoded (their entries are then checked one by one)."""
    events_received: int = 0
    commands_served: int = 0
    decode_errors: int = 0
    last_decode_error: str = ""
    states_refused: int = 0
    """States dropped by the keyed-mode gate (unsigned, forged, stale, replayed, unknown)."""
    events_refused: int = 0
    states_beyond_reach: int = 0
    """States dropped unchecked as beyond the receiver's reach (comms/gate.py step 4b)."""
    states_misplaced: int = 0
    """States refused because their key's grid cell is not their position's, or (relayed) their
    cell is not in the relay block they came in (also decode_errors)."""
    states_superseded: int = 0
    """States a polled subscription dropped unverified: a newer one of their vehicle passed."""
    states_unchecked: int = 0
    """States a polled subscription dropped unchecked: its check budget was spent (a flood)."""
    relay_batches_received: int = 0
    """Batches from the router's cell relay that decoded (comms/relay.py)."""
    rosters_applied: int = 0
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
        auth: MemberAuth | None = None,
        stop: threading.Event | None = None,
        wait_s: float | None = None,
        roster_sync: RosterSyncConfig = RosterSyncConfig(),
    ) -> None:
        """`auth` is a trust.auth.FleetAuth (this member's key and the roster), or None for
        open mode. Raises FleetKeyError if the key is for another fleet. `stop`, `wait_s`: a
        client waiting for its router gives up (MeshUnreachable) once `stop` is set or after
        `wait_s` (comms.session.open_session)."""
        if auth is not None and auth.fleet != cfg.fleet:
            raise FleetKeyError(
                f"the key file is for fleet {auth.fleet!r}, but this process joins "
                f"fleet {cfg.fleet!r}"
            )
        self.cfg = cfg
        self.fleet = cfg.fleet
        self.clock_ns = clock_ns
        self.auth = auth
        self.stats = MeshStats()
        self.gates: list[Gate] = []
        """Every receive gate of this process (keyed mode), for counters."""
        self.on_security: Callable[[str], None] | None = None
        """Gets one-line summaries of refused states/events (rate-limited per cause); the agent
        publishes them as SECURITY events. Default: a log warning."""
        self._unchecked = Summaries(self._summary)  # polled states left unchecked (a flood)
        self._session: zenoh.Session | None = open_session(cfg, stop, wait_s=wait_s)
        self._publishers: dict[int, tuple[keys.Cell, zenoh.Publisher]] = {}
        """Each vehicle's state publisher, on the key of the cell it was last in."""
        self._feed = FeedBuffer(cfg.feed_hz)
        self._feed_pub: zenoh.Publisher | None = None
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self._error_log_ns = 0
        self.roster_sync: DocSync[RosterHead, Roster] | None = None
        """Keyed mode: the roster follower (trust/roster_sync.py), for its counts."""
        self.relay: CellRelay | None = None
        """Router mode: this router's cell relay (comms/relay.py), unless MeshConfig says none."""
        if cfg.mode == "router" and cfg.cell_relay_period_s is not None:
            try:
                self.relay = self._keep(
                    CellRelay(self.session, RelayConfig(cfg.cell_relay_period_s))
                )
            except BaseException:
                self.close()
                raise
        if auth is not None:
            try:
                self.roster_sync = self._keep(
                    auth.follow_roster(
                        self.session,
                        roster_sync,
                        on_summary=self._summary,
                        on_applied=lambda _r: self.stats.bump("rosters_applied"),
                    )
                )
            except BaseException:
                self.close()
                raise

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
        if self._feed_pub is not None:  # best effort: the last states of a closing process
            with contextlib.suppress(Exception):
                for batch in self._feed.flush():
                    self._feed_pub.put(batch)
        with self._lock:
            session, self._session = self._session, None
            entities, self._entities = self._entities, []
            publishers = [pub for _, pub in self._publishers.values()]
            self._publishers.clear()
            if self._feed_pub is not None:
                publishers.append(self._feed_pub)
                self._feed_pub = None
        if session is None:
            return
        entities = publishers + entities
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

    # -- keyed mode ------------------------------------------------------------------------
    def _summary(self, line: str) -> None:
        if self.on_security is not None:
            self.on_security(line)
        else:
            log.warning("SECURITY: %s", line)

    def new_gate(
        self,
        cfg: GateConfig = GateConfig(),
        what: str = "state",
        worth_checking: Callable[[VehicleState], bool] | None = None,
    ) -> Gate:
        if self.auth is None:
            raise RuntimeError("an open-mode mesh has no keys to gate with")
        gate = Gate(
            self.auth, cfg, on_summary=self._summary, what=what, worth_checking=worth_checking
        )
        self.gates.append(gate)
        return gate

    def publish_roster(self, roster: Roster) -> None:
        """Push a roster (the fleet authority's tool: covey keygen push). Members check it."""
        publish_roster(self.session, self.fleet, roster.encode())

    # -- states ----------------------------------------------------------------------------
    def publish_state(
        self,
        state: VehicleState,
        *,
        auth: MemberAuth | None = None,
        receivers: Sequence[int] = (),
    ) -> None:
        """Publish on the key of the state's own grid cell (comms/keys.py); a vehicle that
        crosses into another cell gets a publisher there, and its old one goes. `auth`: the
        vehicle's own FleetAuth when one process hosts several vehicles; default the mesh's.
        `receivers`: the neighbours (nearest first) to tag the state for in keyed mode, so that
        they need not check its signature (trust/links.py); the station's feed gets it untagged."""
        auth = auth if auth is not None else self.auth
        if auth is not None:
            state = auth.sign_state(state, receivers)
        payload = state.encode()  # validated; a signed state's bytes packed once, as signed
        vid, links = state.vehicle_id, state.links
        feed_payload = payload[: len(payload) - 1 - len(links)] if links else payload
        cell = keys.cell_of(state.pos_ned_m)
        held = self._publishers.get(vid)
        if held is None or held[0] != cell:
            pub = self.session.declare_publisher(
                keys.state(self.fleet, vid, cell),
                congestion_control=zenoh.CongestionControl.DROP,
                express=False,
            )
            with self._lock:
                self._publishers[vid] = (cell, pub)
            if held is not None:
                with contextlib.suppress(Exception):
                    held[1].undeclare()
        else:
            pub = held[1]
        pub.put(payload)
        stats = self.stats
        with stats._lock:  # stats.bump("states_sent"), a state at a time
            stats.states_sent += 1
        batches = self._feed.offer(vid, feed_payload, self.clock_ns())
        if batches:
            self._send_feed(vid, batches)

    def _send_feed(self, vehicle_id: int, batches: list[bytes]) -> None:
        """Put due feed batches on this process's feed key (that of its first vehicle)."""
        if not batches:
            return
        with self._lock:
            if self._feed_pub is None:
                self._feed_pub = self.session.declare_publisher(
                    keys.feed(self.fleet, vehicle_id),
                    congestion_control=zenoh.CongestionControl.DROP,
                    express=True,
                )
            pub = self._feed_pub
        for batch in batches:
            pub.put(batch)
        self.stats.bump("feed_batches_sent", len(batches))

    def subscribe_states(
        self,
        callback: StateCallback,
        vehicle_id: int | None = None,
        link: StateLink | None = None,
        *,
        on_refused: RefusedCallback | None = None,
        gate: GateConfig = GateConfig(),
        ignore_id: int | None = None,
    ) -> Any:
        """Call `callback(state, recv_ns)` for every valid state of the fleet (or of
        `vehicle_id`), in every cell. `link` (comms.link) stands between the wire and the
        callback and emulates a radio per sender: it may drop, delay or thin states, and calls
        `link.offer(state, recv_ns, deliver)` instead of the callback.

        Keyed mode: only states that pass a Gate(`gate`) reach the callback; `on_refused(vid,
        cause, recv_ns)` hears of the others (the ground station passes its FleetModel's
        `on_state_refused`).
        `ignore_id`: drop this vehicle's states unchecked (an agent's own, echoed back)."""
        key = (
            keys.all_states(self.fleet)
            if vehicle_id is None
            else keys.vehicle_states(self.fleet, vehicle_id)
        )
        admit = self._admitters(callback, link, on_refused, gate, ignore_id)[0]
        return self._keep(self.session.declare_subscriber(key, self._state_handler(admit)))

    def subscribe_cells(
        self,
        callback: StateCallback,
        cells: Iterable[keys.Cell] = (),
        link: StateLink | None = None,
        *,
        on_refused: RefusedCallback | None = None,
        gate: GateConfig = GateConfig(),
        ignore_id: int | None = None,
        remote_only: bool = False,
        worth_checking: Callable[[VehicleState], bool] | None = None,
        polled: bool = False,
        relay_for: int | None = None,
    ) -> CellSubscription:
        """As `subscribe_states`, but only the states of the grid cells `cells`; move the
        subscription with `.set_cells(cells)` (comms/scope.py says which cells). One gate and one
        handler serve every cell, so a state replayed into another cell is still a replay.
        `remote_only`: never deliver this session's own states (a process of many vehicles).
        `worth_checking(state)`: False drops a state before its signature check (or, in open
        mode, before the callback): comms/gate.py step 4b, e.g. `NeighbourTable.worth_checking`.
        `polled`: nothing runs on Zenoh's threads; the states wait in a ring per cell until the
        owner's `drain()` (an agent's tick) takes them all at once (`_state_batch_handler`).
        `relay_for` (polled, one vehicle's id): hear the cells through the router's cell relay
        while it has one (comms/relay.py), one message a relay period instead of one per state."""
        admit, admit_heard = self._admitters(
            callback, link, on_refused, gate, ignore_id, worth_checking
        )
        sub = CellSubscription(
            self,
            self._state_handler(admit) if not polled else None,
            remote_only,
            self._state_batch_handler(admit_heard, link is not None, gate.batch_budget_s)
            if polled
            else None,
            relay_for,
        )
        sub.set_cells(cells)
        return self._keep(sub)

    def subscribe_feed(
        self,
        callback: FeedCallback,
        link: StateLink | None = None,
        *,
        on_refused: RefusedCallback | None = None,
        gate: GateConfig = GateConfig(),
    ) -> Any:
        """Call `callback(state, recv_ns, entry_seq)` for every valid state in the fleet's feeds:
        the latest state of every vehicle, batched per process at its MeshConfig.feed_hz
        (comms/feed.py), which is the whole fleet at a load a ground station can carry. Each
        entry passes exactly the checks a state on its own key passes (`subscribe_states`: the
        keyed-mode gate, `on_refused`, `link`), but for the cell: an entry may be in any cell.
        A malformed batch is refused whole with the reason; a bad entry costs only itself."""
        admit = self._admitters(callback, link, on_refused, gate, None)[0]

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            where = str(sample.key_expr)
            try:
                if keys.parse_feed_key(where) is None:
                    raise DecodeError(f"a feed batch arrived on {where}, which is no feed key")
                batch = FeedBatch.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self._bad(where, exc)
                return
            self.stats.bump("feed_batches_received")
            for i, entry in enumerate(batch.entries):
                try:
                    state = VehicleState.decode(entry.state)
                except DecodeError as exc:
                    self._bad(f"{where} entry {i}", exc)
                    continue
                admit(state, recv_ns, (entry.entry_seq,))

        return self._keep(self.session.declare_subscriber(keys.all_feeds(self.fleet), on_sample))

    def _state_handler(self, admit: Admit) -> Callable[[zenoh.Sample], None]:
        """A state key's sample: decoded, on its own vehicle's key and cell, then admitted."""

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            state = self._decode_state(str(sample.key_expr), sample.payload.to_bytes())
            if state is not None:
                admit(state, recv_ns, ())

        return on_sample

    def _state_batch_handler(
        self, admit: AdmitHeard, every_state: bool, budget_s: float
    ) -> Callable[[list[Heard], int, int], None]:
        """`_state_handler` for the states a polled subscription took at once
        (`CellSubscription.drain`; each decoded only when tried: comms/heard.py): each checked
        as one would be, its receive time
        estimated from the lags of its sender's states that went on (comms/arrival.py; a forged
        stamp cannot move it). `every_state` (a link, which judges every state it
        hears): every state goes on, in order. Otherwise only the newest state of each vehicle
        that passes the gate goes on, the older ones of that vehicle dropped unverified
        (`states_superseded`), and the candidates are tried in rounds: first each vehicle's most
        plausible (newest first among those not stamped later than its verified states ever
        arrived, `PLAUSIBLE_LAG_SLACK_NS`: a forger's future stamps go last), then each one's
        next, and so on while less than `budget_s` was spent; what is left is dropped unchecked
        (`states_unchecked`). A forged state thus costs its check but cannot hide a real one
        unless it floods past the budget, and a flood cannot stall the tick."""
        arrival = ArrivalEstimate()  # the least lag of each sender's states that went on
        least_of, note = arrival.least_ns, arrival.note

        def on_states(states: list[Heard], taken_ns: int, since_ns: int) -> None:
            if every_state:
                got: list[tuple[Heard, int]] = []
                for state in states:
                    recv_ns = arrival.estimate_ns(
                        state.vehicle_id, state.stamp_ns, taken_ns, since_ns
                    )
                    got.append((state, recv_ns))
                for state, recv_ns in got:
                    if admit(state, recv_ns):
                        note(state.vehicle_id, taken_ns - state.stamp_ns, taken_ns)
                return
            # Each vehicle's states in the order they came, and its least lag as it was before
            # this batch (each receive time is estimated from it, `estimated_ns`, when tried)
            by_vehicle: dict[int, list[Heard]] = {}
            for state in states:
                candidates = by_vehicle.get(state.vehicle_id)
                if candidates is None:
                    by_vehicle[state.vehicle_id] = [state]
                else:
                    candidates.append(state)
            rounds: list[tuple[list[Heard], int | None]] = []
            for vid, candidates in by_vehicle.items():
                least_ns = least_of(vid)
                if len(candidates) > 1:
                    # implausible: taken_ns - stamp < least_ns - PLAUSIBLE_LAG_SLACK_NS
                    late_ns = (
                        None if least_ns is None else taken_ns - least_ns + PLAUSIBLE_LAG_SLACK_NS
                    )
                    if _rising(candidates) and (
                        late_ns is None or candidates[-1].stamp_ns <= late_ns
                    ):
                        candidates.reverse()  # as they usually come: the sort's order, at once
                    elif late_ns is None:
                        candidates.sort(key=_newest_first)
                    else:
                        candidates.sort(key=functools.partial(_plausible_newest_first, late_ns))
                rounds.append((candidates, least_ns))
            t0_s = time.perf_counter()
            superseded = unchecked = 0
            k = 0
            while rounds:
                left = []
                for entry in rounds:
                    candidates, least_ns = entry
                    if k and time.perf_counter() - t0_s > budget_s:
                        unchecked += len(candidates) - k
                        continue
                    state = candidates[k]
                    stamp_ns = state.stamp_ns
                    if admit(state, estimated_ns(least_ns, stamp_ns, taken_ns, since_ns)):
                        note(state.vehicle_id, taken_ns - stamp_ns, taken_ns)
                        superseded += len(candidates) - k - 1
                    elif k + 1 < len(candidates):
                        left.append(entry)
                rounds, k = left, k + 1
            if superseded:
                self.stats.bump("states_superseded", superseded)
            if unchecked:
                self.stats.bump("states_unchecked", unchecked)
                self._unchecked.note(
                    "unchecked",
                    taken_ns,
                    lambda n: (
                        f"{n} time(s) states were left unchecked: their checks took more than "
                        f"{budget_s * 1e3:.0f} ms of a tick (a flood of forged states?)"
                    ),
                )

        return on_states

    def _decode_state(
        self, key: str, payload: bytes, block: tuple[int, keys.Cell] | None = None
    ) -> VehicleState | None:
        """A state's payload decoded, on its own vehicle's key and cell (or, relayed, in its
        relay block: comms/relay.py `decode_placed`); None (counted and reported) if not."""
        try:
            return decode_placed(key, payload, block)
        except DecodeError as exc:
            if isinstance(exc, MisplacedState):
                self.stats.bump("states_misplaced")
            self._bad(key, exc)
            return None

    def _heard(
        self, key: str, payload: bytes, block: tuple[int, keys.Cell] | None = None, place: int = 0
    ) -> Heard | None:
        """A polled state's payload with its head read (comms/heard.py), to be decoded when
        tried; None (its decode's reason counted and reported) if its head is not a state's."""
        heard = Heard.of(key, payload, block, place)
        if heard is None:
            self._decode_state(heard_at(key, block, place), payload, block)  # says why not
        return heard

    def _decode_heard(self, heard: Heard) -> VehicleState | None:
        """`heard` decoded and placed (`_decode_state`); None (counted and reported) if not."""
        return self._decode_state(heard.where, heard.payload, heard.block)

    def _hear_relayed(self, sample: zenoh.Sample, block: tuple[int, keys.Cell]) -> list[Heard]:
        """The states of a relay batch (comms/relay.py), each heard on its own (decoded and
        placed when tried): a bad one costs only itself; a malformed batch is refused whole."""
        key = str(sample.key_expr)
        try:
            batch = RelayBatch.decode(sample.payload.to_bytes())
        except DecodeError as exc:
            self._bad(key, exc)
            return []
        self.stats.bump("relay_batches_received")
        got, bad = hear_all(key, batch.states, block)
        for i in bad:  # its decode says why not (`_heard`)
            self._decode_state(heard_at(key, block, i), batch.states[i], block)
        return got

    def _admitters(
        self,
        callback: Callable[..., None],
        link: StateLink | None,
        on_refused: RefusedCallback | None,
        gate: GateConfig,
        ignore_id: int | None,
        worth_checking: Callable[[VehicleState], bool] | None = None,
    ) -> tuple[Admit, AdmitHeard]:
        """What every state passes, whichever way it came (its own key, a feed entry, a polled
        subscription's drain), one gate per subscription: `admit` takes a decoded state (the
        echo filter, the keyed-mode gate with refusals counted and told to `on_refused`, then
        the link and `callback(state, recv_ns, *extra)`); `admit_heard` the same for a heard
        one (comms/heard.py), the gate's checks of its head before its decode."""
        if worth_checking is not None:
            worth_checking = self._counted(worth_checking)
        checker = (
            self.new_gate(gate, worth_checking=worth_checking) if self.auth is not None else None
        )

        stats = self.stats

        def dropped(vid: int, verdict: Refusal | str, recv_ns: int) -> bool:
            if isinstance(verdict, Refusal):
                stats.bump("states_refused")
                if on_refused is not None:
                    _guarded(on_refused, vid, verdict.value, recv_ns)
            return False

        def deliver(state: VehicleState, recv_ns: int, extra: tuple) -> bool:
            """A state that passed every check: counted, then to the link or the callback."""
            with stats._lock:
                stats.states_received += 1
            if link is not None:
                link.offer(state, recv_ns, lambda s, t: _guarded(callback, s, t, *extra))
                return True
            try:  # _guarded, inline: every state that goes on comes here
                callback(state, recv_ns, *extra)
            except Exception:  # noqa: BLE001 - a subscriber bug must not kill Zenoh's thread
                log.exception("subscriber callback failed")
            return True

        def go_on(state: VehicleState, recv_ns: int, extra: tuple) -> bool:
            """The checks of a decoded state, then delivery."""
            if checker is None and worth_checking is not None and not worth_checking(state):
                return False  # open mode: nothing to verify, but no use for it either
            if checker is not None:
                verdict = checker.admit_state(state, recv_ns)
                if verdict is not None:
                    return dropped(state.vehicle_id, verdict, recv_ns)
            return deliver(state, recv_ns, extra)

        def admit(state: VehicleState, recv_ns: int, extra: tuple) -> bool:
            """True: `state` went on; False: dropped (an echo, beyond reach, thinned, refused)."""
            if state.vehicle_id == ignore_id:
                return False
            return go_on(state, recv_ns, extra)

        if checker is None:

            def admit_heard(heard: Heard, recv_ns: int) -> bool:
                """`admit` for a heard state (open mode: decoded, then as `admit`)."""
                if heard.vehicle_id == ignore_id:
                    return False
                state = self._decode_heard(heard)
                return state is not None and go_on(state, recv_ns, ())

            return admit, admit_heard

        admit_head, admit_decoded = checker.admit_head, checker.admit_decoded

        def admit_keyed(heard: Heard, recv_ns: int) -> bool:
            """`admit` for a heard state, decoded only if its head passes the gate's checks
            (`Gate.admit_head`), then the rest of them (`admit_decoded`, on the signed bytes
            the state was decoded from: `VehicleState.signed_bytes` of it, without packing
            them again)."""
            vid, seq, stamp_ns, signed, payload, key, block, place = heard
            if vid == ignore_id:
                return False
            verdict = admit_head(vid, seq, stamp_ns, signed, recv_ns)
            if verdict is None:
                state = self._decode_state(heard_at(key, block, place), payload, block)
                if state is None:
                    return False
                verdict = admit_decoded(state, recv_ns, payload[:_SIGNED_BYTES])
                if verdict is None:
                    return deliver(state, recv_ns, ())
            return dropped(vid, verdict, recv_ns)

        return admit, admit_keyed

    def _counted(
        self, worth_checking: Callable[[VehicleState], bool]
    ) -> Callable[[VehicleState], bool]:
        """`worth_checking`, its refusals counted in `stats.states_beyond_reach`."""

        def counted(state: VehicleState) -> bool:
            if worth_checking(state):
                return True
            self.stats.bump("states_beyond_reach")
            return False

        return counted

    # -- events ----------------------------------------------------------------------------
    def publish_event(self, event: Event, *, auth: MemberAuth | None = None) -> None:
        """Publish `event`, signed with `auth` (its vehicle's own FleetAuth when one process
        hosts several vehicles; default the mesh's)."""
        auth = auth if auth is not None else self.auth
        if auth is not None:
            event = auth.sign_event(event)
        self.session.put(keys.event(self.fleet, event.vehicle_id or 1), event.encode())

    def event(
        self, vehicle_id: int, text: str, *, auth: MemberAuth | None = None, **kw: Any
    ) -> None:
        event = Event(vehicle_id=vehicle_id, stamp_ns=self.clock_ns(), text=text, **kw)
        self.publish_event(event, auth=auth)

    def publish_outcome(self, outcome: ActionOutcome, *, auth: MemberAuth | None = None) -> None:
        """Publish how a command's autopilot part ended, signed as `publish_event` signs, on
        the vehicle's event key (its subscribers get it through `subscribe_events`)."""
        auth = auth if auth is not None else self.auth
        if auth is not None:
            outcome = auth.sign_outcome(outcome)
        self.session.put(keys.event(self.fleet, outcome.vehicle_id), outcome.encode())

    def subscribe_events(
        self, callback: EventCallback, on_outcome: OutcomeCallback | None = None
    ) -> Any:
        """Call `callback(event, recv_ns)` for every valid event of the fleet, and
        `on_outcome(outcome, recv_ns)` for every autopilot outcome (None: outcomes are
        dropped unread). Keyed mode: both pass one Gate (signed by their vehicle, fresh)."""
        checker = self.new_gate(what="event") if self.auth is not None else None

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            try:
                ev = decode_event_message(sample.payload.to_bytes())
            except DecodeError as exc:
                self._bad(str(sample.key_expr), exc)
                return
            deliver = callback if isinstance(ev, Event) else on_outcome
            if deliver is None:
                return
            if checker is not None and checker.admit_event(ev, recv_ns) is not None:
                self.stats.bump("events_refused")
                return
            self.stats.bump("events_received")
            _guarded(deliver, ev, recv_ns)

        return self._keep(self.session.declare_subscriber(keys.all_events(self.fleet), on_sample))

    # -- guidance traces -------------------------------------------------------------------
    def publish_trace(self, trace: GuidanceTrace) -> None:
        """Publish what guidance saw and commanded in one tick, signed in keyed mode, on the
        vehicle's trace key. Recorders keep it for closed-loop replay; nothing live follows it,
        and a full network drops it rather than wait."""
        if self.auth is not None:
            trace = self.auth.sign_trace(trace)
        self.session.put(
            keys.trace(self.fleet, trace.vehicle_id),
            trace.encode(),
            congestion_control=zenoh.CongestionControl.DROP,
        )

    # -- presence --------------------------------------------------------------------------
    def declare_vehicle(self, vehicle_id: int) -> zenoh.LivelinessToken:
        """Announce this process as vehicle `vehicle_id` until the token is undeclared."""
        return self._keep(
            self.session.liveliness().declare_token(keys.alive(self.fleet, vehicle_id))
        )

    def declare_gcs(self, gcs_id: int) -> zenoh.LivelinessToken:
        return self._keep(
            self.session.liveliness().declare_token(keys.gcs_alive(self.fleet, gcs_id))
        )

    def presence(
        self,
        on_change: Callable[[str, int, bool], None] | None = None,
    ) -> Presence:
        """Track which vehicles and ground stations are alive. `on_change(kind, id, alive)` is
        called with kind "vehicle" or "gcs"; a late joiner sees everyone already there."""
        pres = Presence(self.fleet, on_change=on_change, clock_ns=self.clock_ns)
        lv = self.session.liveliness()
        self._keep(lv.declare_subscriber(keys.all_alive(self.fleet), pres.on_sample, history=True))
        self._keep(
            lv.declare_subscriber(keys.all_gcs_alive(self.fleet), pres.on_sample, history=True)
        )
        return pres

    # -- commands --------------------------------------------------------------------------
    def serve_commands(
        self,
        vehicle_id: int,
        handler: CommandHandler,
        *,
        auth: MemberAuth | None = None,
        polled: bool = False,
        on_mission: MissionHandler | None = None,
        wake: threading.Event | None = None,
    ) -> Any:
        """Answer commands for `vehicle_id`; `handler` returns the ack (never raise from it:
        an exception becomes a FAILED ack with the exception text). `auth`: that vehicle's own
        FleetAuth when one process serves several vehicles (`covey agent --ids`); default the mesh's.

        `polled`: the queries wait in a bounded ring (`COMMAND_RING`, the oldest dropped when
        full) and are answered when the caller calls `poll()` on the returned `PolledCommands`,
        on the caller's own thread. A process of many vehicles answers from its tick loop: a
        command to all then costs no thread wake-ups, where a callback queryable is one Zenoh
        handler thread per vehicle, all woken at once (docs/scaling.md). Otherwise the answer
        is given at once, on that handler thread. `wake` (polled only): set as each query comes,
        so that a loop resting between slow ticks answers at once (kit/ticks.py).

        A Mission uploaded on the same key passes the same checks (`auth.check_mission`) and
        goes to `on_mission`; without one it is refused ("does not fly missions")."""
        reply_key = keys.cmd(self.fleet, vehicle_id)
        auth = auth if auth is not None else self.auth
        ack_key = keys.ack(self.fleet, vehicle_id)

        def ack(nonce: int, result: AckResult, reason: str) -> CommandAck:
            return CommandAck(vehicle_id, nonce, self.clock_ns(), result, reason[:96], Mode.LANDED)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                is_mission = payload[:1] == bytes([MsgType.MISSION])
                command = (Mission if is_mission else Command).decode(payload)
            except DecodeError as exc:
                self._bad(reply_key, exc)
                answer = ack(0, AckResult.REJECTED, f"malformed command: {exc}")
            else:
                if not command.applies_to(vehicle_id):
                    if str(query.key_expr) != reply_key:
                        return  # a multi-vehicle query (v/*/cmd) for others: not ours to answer
                    # Sent to this vehicle by name but addressed to others: a retargeting attempt
                    # or a station bug. Say so, signed, instead of staying silent.
                    why = f"not for this vehicle: addressed to {', '.join(map(str, command.targets[:8]))}"
                    if auth is not None:
                        auth.refuse(command, vehicle_id, why)
                    answer = ack(command.nonce, AckResult.REJECTED, why)
                    self._answer(query, reply_key, ack_key, answer, payload, auth)
                    return
                self.stats.bump("commands_served")
                if auth is None:
                    problem = None
                elif isinstance(command, Mission):
                    problem = auth.check_mission(command, vehicle_id)
                else:
                    problem = auth.check_command(command, vehicle_id)
                if problem:
                    answer = ack(command.nonce, AckResult.REJECTED, problem)
                else:
                    try:
                        if isinstance(command, Command):
                            answer = handler(command)
                        elif on_mission is not None:
                            answer = on_mission(command)
                        else:
                            answer = ack(
                                command.nonce,
                                AckResult.REJECTED,
                                "this vehicle does not fly missions",
                            )
                    except Exception as exc:  # noqa: BLE001 - a handler bug must not kill the agent
                        log.exception("command handler failed")
                        answer = ack(command.nonce, AckResult.FAILED, f"internal error: {exc}")
            self._answer(query, reply_key, ack_key, answer, payload, auth)

        if polled and wake is not None:
            inbox: collections.deque[zenoh.Query] = collections.deque(maxlen=COMMAND_RING)

            def ring_bell(query: zenoh.Query) -> None:  # on Zenoh's thread: keep it, wake the loop
                inbox.append(query)  # the oldest dropped when full, as the ring does
                wake.set()

            bell = zenoh.handlers.Callback(ring_bell, indirect=False)
            qbl = self._keep(self.session.declare_queryable(reply_key, bell))
            return PolledCommands(qbl, on_query, inbox)
        if polled:
            ring: zenoh.handlers.RingChannel[zenoh.Query] = zenoh.handlers.RingChannel(COMMAND_RING)
            return PolledCommands(
                self._keep(self.session.declare_queryable(reply_key, ring)), on_query
            )
        return self._keep(self.session.declare_queryable(reply_key, on_query))

    def _answer(
        self,
        query: zenoh.Query,
        reply_key: str,
        ack_key: str,
        answer: CommandAck,
        command_payload: bytes,
        auth: MemberAuth | None,
    ) -> None:
        if auth is not None:
            answer = auth.sign_ack(answer, command_digest(command_payload))
        payload = answer.encode()
        try:
            query.reply(reply_key, payload)
        except Exception as exc:  # noqa: BLE001 - the querier may be gone
            log.warning("could not reply to a command: %s", exc)
        try:  # the copy for recorders and other stations (comms/keys.py says why both)
            self.session.put(ack_key, payload)
        except Exception as exc:  # noqa: BLE001
            log.warning("could not publish the ack copy: %s", exc)

    def observe_commands(
        self,
        on_command: Callable[[Command | Mission, int, bytes], None],
        on_ack: Callable[[CommandAck, int], None],
    ) -> None:
        """See every command and mission upload sent to the fleet, from any station, with its
        receive stamp and the digest its acks are bound to (`auth.command_digest`), and every
        vehicle's ack copy (`msg/<id>/ack`). A silent queryable (complete=False) sees each
        command query and never replies, so the vehicles' answers to the sender are untouched."""

        def on_query(query: zenoh.Query) -> None:
            recv_ns = self.clock_ns()
            payload = query.payload.to_bytes() if query.payload else b""
            kind = Mission if payload[:1] == bytes([MsgType.MISSION]) else Command
            try:
                command = kind.decode(payload)
            except DecodeError as exc:
                self._bad(str(query.key_expr), exc)
                return
            _guarded(on_command, command, recv_ns, command_digest(payload))

        def on_sample(sample: zenoh.Sample) -> None:
            recv_ns = self.clock_ns()
            try:
                ack = CommandAck.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self._bad(str(sample.key_expr), exc)
                return
            _guarded(on_ack, ack, recv_ns)

        self._keep(
            self.session.declare_queryable(keys.all_cmds(self.fleet), on_query, complete=False)
        )
        self._keep(self.session.declare_subscriber(keys.all_acks(self.fleet), on_sample))

    def send_command(
        self,
        command: Command | Mission,
        *,
        expect: Iterable[int] | None = None,
        timeout_s: float = 2.0,
    ) -> CommandResult:
        """Send one command in ONE query and collect every vehicle's answer.

        `expect`: the vehicles that should answer (default: `command.targets`). A vehicle in it
        that does not answer in time is reported as TIMEOUT. Answers from others are kept too.
        A Mission goes the same way (an upload, acked per vehicle), signed as a mission.
        """
        if not 0.0 < timeout_s <= 60.0:
            raise ValueError(f"timeout_s={timeout_s} must be within (0, 60]")
        if self.auth is not None:
            if isinstance(command, Mission):
                command = self.auth.sign_mission(command)
            else:
                command = self.auth.sign_command(command)
        payload = command.encode()
        digest = command_digest(payload)
        expected = set(command.targets if expect is None else expect)
        waiting = set(expected)
        key = (
            keys.cmd(self.fleet, command.targets[0])
            if len(command.targets) == 1
            else keys.all_cmds(self.fleet)
        )
        t0 = time.monotonic()
        outcomes: dict[int, Outcome] = {}
        verified: set[int] = set()  # a forged ack arriving later must not overwrite a real one
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
            problem = self.auth.check_ack(ack, command, digest) if self.auth else None
            if ack.nonce != command.nonce and ack.nonce != 0:
                problem = (
                    f"forged ack: nonce {ack.nonce} does not match command nonce {command.nonce}"
                )
            if problem:
                errors.append(f"vehicle {ack.vehicle_id}: {problem}")
                log.warning("vehicle %d: %s", ack.vehicle_id, problem)
                if ack.vehicle_id not in outcomes or ack.vehicle_id not in verified:
                    outcomes[ack.vehicle_id] = Outcome(
                        ack.vehicle_id, OutcomeStatus.ERROR, problem, ack, latency_s
                    )
                continue
            verified.add(ack.vehicle_id)
            outcomes[ack.vehicle_id] = Outcome.from_ack(ack, latency_s)
            waiting.discard(ack.vehicle_id)
            if expected and not waiting:  # O(1) per ack: a 500-vehicle broadcast stays linear
                break
        elapsed_s = time.monotonic() - t0
        # The query ends early when every reachable queryable has answered: a vehicle missing
        # then is not on the mesh at all; one missing at the deadline is on it but silent.
        why = (
            f"no answer within {timeout_s:g} s"
            if elapsed_s >= 0.9 * timeout_s
            else "not reachable on the mesh"
        )
        for vid in sorted(expected - outcomes.keys()):
            outcomes[vid] = Outcome(vid, OutcomeStatus.TIMEOUT, why, None, elapsed_s)
        return CommandResult(command=command, outcomes=outcomes, errors=tuple(errors))


COMMAND_RING = 64
PLAUSIBLE_LAG_SLACK_NS = 50_000_000
"""A polled state stamped more than this later than its sender's verified states ever arrived
is tried after its vehicle's others (a forger's future stamps; real ones jitter less)."""
"""Queries a polled command queryable holds between two polls (`Mesh.serve_commands`): a
vehicle gets a few commands a second, so only a flood fills it, and then the oldest go (their
senders see no ack) rather than Zenoh's network thread waiting for room."""


class PolledCommands:
    """One vehicle's command queryable whose queries wait until `poll()` answers them: in
    Zenoh's ring, or, with a doorbell (`serve_commands(wake=...)`), in `inbox`."""

    def __init__(
        self,
        queryable: Any,
        answer: Callable[[zenoh.Query], None],
        inbox: collections.deque | None = None,
    ) -> None:
        self._queryable, self._answer, self._inbox = queryable, answer, inbox

    def _next(self) -> zenoh.Query | None:
        if self._inbox is None:
            return self._queryable.try_recv()
        try:
            return self._inbox.popleft()
        except IndexError:
            return None

    def poll(self) -> int:
        """Answer every query that came since the last poll, in order; returns how many."""
        n = 0
        while (query := self._next()) is not None:
            self._answer(query)
            n += 1
        return n


class CellSubscription:
    """The state subscribers of a set of grid cells, one Zenoh subscriber per cell, that share
    one handler, plus one for unplaced states. Thread-safe; undeclared with the mesh.

    Called back (`on_sample`, on Zenoh's threads) or polled (`on_states`: each subscriber keeps
    what came in a ring of `POLL_RING` samples, the oldest dropped when full, never blocking
    Zenoh; `drain()` takes them all and hands them over at once, each decoded when tried).

    Polled, for one vehicle (`relay_for`, its id) that is a client or peer of a router with a
    cell relay (comms/relay.py): when the cells are a relay block (the square comms/scope.py
    gives one vehicle), it wants that block from the relay and hears it as one message a relay
    period instead of one per state. Its own cell subscribers stay until two batches have come
    (make before break), and come back while the relay is silent for RELAY_SILENT_S (it went,
    or the router has none)."""

    POLL_RING = 4096
    """Samples kept per polled cell between two drains: 4 s of 100 vehicles at 10 Hz."""
    RELAY_RING = 256
    """Relay batches kept between two drains."""
    RELAY_SETTLE_BATCHES = 2
    """Batches heard on a block before its own cell subscribers go: the relay had subscribed
    to the block's cells for a whole period."""

    def __init__(
        self,
        mesh: Mesh,
        on_sample: Callable[[zenoh.Sample], None] | None,
        remote_only: bool,
        on_states: Callable[[list[Heard], int, int], None] | None = None,
        relay_for: int | None = None,
    ) -> None:
        if (on_sample is None) == (on_states is None):
            raise ValueError("a cell subscription is either called back or polled")
        if relay_for is not None and on_states is None:
            raise ValueError("only a polled cell subscription hears a relay")
        self._mesh = mesh
        self._on_sample = on_sample
        self._on_states = on_states
        self._drained_ns = mesh.clock_ns()  # when the rings were last emptied
        self._origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
        self._lock = threading.Lock()
        self._want: frozenset[keys.Cell] = frozenset()
        self._want_block: tuple[frozenset[keys.Cell], tuple[int, keys.Cell] | None] = (
            self._want,
            None,
        )
        """`_want` and its `keys.block_of`, worked out once per `set_cells`, not per drain."""
        self._subs: dict[keys.Cell, Any] = {}
        self._retired: list[Any] = []  # polled: left cells' subscribers, until the next drain
        self.changes = 0
        """Cell subscribers declared plus undeclared since start (read only)."""
        # The relay of this session's router, if it has one (comms/relay.py).
        self._relay_for = relay_for
        self._relay_id: str | None = None
        self._block_of: tuple[str | None, tuple[int, keys.Cell] | None] = (None, None)
        self._looked_ns = mesh.clock_ns()  # when the session's routers were last looked at
        self._block: tuple[int, keys.Cell] | None = None  # the block wanted from it
        self._block_sub: Any = None
        self._want_token: Any = None
        self._block_batches = 0  # batches heard on this block since it was wanted or silent
        self._block_heard_ns = 0
        self._said_relayed = False
        self._retired_blocks: list[tuple[tuple[int, keys.Cell], Any]] = []
        # States put without a cell (tools, an older member) are heard everywhere, as before
        # scoping, so that nothing can hide by leaving its cell out; covey publishers place theirs.
        self._unplaced = self._declare(keys.unplaced_states(mesh.fleet))
        if relay_for is not None:
            self._relay_id = self._router()

    def _router(self) -> str | None:
        """The Zenoh id of this session's (first) router, whose relay it would hear."""
        routers = [str(z) for z in self._mesh.session.info.routers_zid()]
        return routers[0] if routers else None

    def _find_relay(self, now_ns: int) -> None:
        """While there is no router, or its relay is silent: every RELAY_SILENT_S, look again
        which router this session is linked to (a router that restarted has a new id; a peer
        may find one later)."""
        if self._relay_for is None or now_ns - self._looked_ns < RELAY_SILENT_S * 1e9:
            return
        silent = self._block is not None and self._block_batches < self.RELAY_SETTLE_BATCHES
        if self._relay_id is None or silent:
            self._looked_ns = now_ns
            with contextlib.suppress(Exception):  # a closing session: keep what we had
                self._relay_id = self._router() or self._relay_id

    def _declare(self, key: str) -> Any:
        handler: Any = self._on_sample
        if handler is None:
            handler = zenoh.handlers.RingChannel(self.POLL_RING)
        return self._mesh.session.declare_subscriber(key, handler, allowed_origin=self._origin)

    @property
    def cells(self) -> frozenset[keys.Cell]:
        with self._lock:
            return self._want

    @property
    def relayed(self) -> bool:
        """The relay delivers these cells now (this subscription's own cell subscribers went)."""
        with self._lock:
            return self._block is not None and not self._subs and bool(self._want)

    def set_cells(self, cells: Iterable[keys.Cell]) -> None:
        """Hear exactly `cells`: new cells are declared before old ones go (make before break).
        Polled: an old cell's subscriber goes at the next drain, which takes what it still holds."""
        want = frozenset(keys.check_cell(tuple(c)) for c in cells)
        with self._lock:
            self._want = want
            gone = self._apply(self._mesh.clock_ns())
        for sub in gone:
            with contextlib.suppress(Exception):
                sub.undeclare()

    def _apply(self, now_ns: int) -> list[Any]:
        """Declare what `_want` needs now: the relay's block and/or this subscription's own cell
        subscribers. Lock held; returns the entities to undeclare now (the rest retire)."""
        gone: list[Any] = []
        self._find_relay(now_ns)
        if self._want_block[0] is not self._want:
            self._want_block = (self._want, keys.block_of(self._want))
        block = self._want_block[1] if self._relay_id is not None else None
        if (self._relay_id, block) != self._block_of:
            self._block_of = (self._relay_id, block)
            if self._want_token is not None:
                gone.append(self._want_token)
            if self._block_sub is not None:  # what it still holds is taken at the next drain
                assert self._block is not None
                self._retired_blocks.append((self._block, self._block_sub))
            self._block_sub = self._want_token = None
            self._block, self._block_batches = block, 0
            if block is not None:
                assert self._relay_for is not None and self._relay_id is not None
                session, fleet = self._mesh.session, self._mesh.fleet
                self._block_sub = session.declare_subscriber(
                    keys.relay_block(fleet, self._relay_id, *block),
                    zenoh.handlers.RingChannel(self.RELAY_RING),
                )
                self._want_token = session.liveliness().declare_token(
                    keys.relay_want(fleet, self._relay_for, self._relay_id, *block)
                )
                self._block_heard_ns = now_ns
        silent = block is not None and now_ns - self._block_heard_ns > RELAY_SILENT_S * 1e9
        if silent:
            self._block_batches = 0  # hear the cells ourselves until it settles again
        relayed = block is not None and self._block_batches >= self.RELAY_SETTLE_BATCHES
        if relayed and not self._said_relayed:
            self._said_relayed = True
            log.info("hearing its cells through router %s's cell relay", self._relay_id)
        elif silent and self._said_relayed:
            self._said_relayed = False
            log.warning(
                "router %s's cell relay was silent for %.1f s: hearing the cells directly",
                self._relay_id,
                RELAY_SILENT_S,
            )
        own = set() if relayed else self._want
        left = []
        for cell in sorted(own - self._subs.keys()):
            self._subs[cell] = self._declare(keys.cell_states(self._mesh.fleet, cell))
            self.changes += 1
        for cell in [c for c in self._subs if c not in own]:
            left.append(self._subs.pop(cell))
            self.changes += 1
        if self._on_states is not None:
            self._retired.extend(left)
            return gone
        return gone + left

    def drain(self, taken_ns: int | None = None) -> int:
        """Polled: take every sample that came since the last drain and hand the states to the
        handler, at once, as taken at `taken_ns` (default now, the mesh's clock), each with its
        head read (comms/heard.py: the handler decodes those it tries); returns how many
        samples (a relay batch is one). Called back: 0."""
        if self._on_states is None:
            return 0
        now_ns = self._mesh.clock_ns() if taken_ns is None else taken_ns
        # The relay's batches first: whether the relay is silent is judged on what came, not on
        # how long since the last drain (a calm vehicle ticks at 1 Hz, its relay at 10).
        with self._lock:
            block, block_sub = self._block, self._block_sub
        batches = []
        if block is not None and block_sub is not None:
            while (sample := block_sub.try_recv()) is not None:
                batches.append((block, sample))
        with self._lock:
            if batches and self._block_sub is block_sub:
                self._block_batches += len(batches)
                self._block_heard_ns = now_ns
            gone = self._apply(now_ns)
            retired, self._retired = self._retired, []
            subs = [*retired, self._unplaced, *self._subs.values()]
            old_blocks, self._retired_blocks = self._retired_blocks, []
        samples = []
        for sub in subs:
            while (sample := sub.try_recv()) is not None:
                samples.append(sample)
        for old, old_sub in old_blocks:
            while (sample := old_sub.try_recv()) is not None:
                batches.append((old, sample))
        since_ns, self._drained_ns = self._drained_ns, now_ns
        for sub in [*retired, *gone, *(b[1] for b in old_blocks)]:
            with contextlib.suppress(Exception):
                sub.undeclare()
        states = []
        for sample in samples:
            heard = self._mesh._heard(str(sample.key_expr), sample.payload.to_bytes())
            if heard is not None:
                states.append(heard)
        for where, sample in batches:
            states += self._mesh._hear_relayed(sample, where)
        if states:
            self._on_states(states, now_ns, since_ns)
        return len(samples) + len(batches)

    def undeclare(self) -> None:
        with self._lock:
            subs = [*self._retired, self._unplaced, *self._subs.values()]
            subs += [e for e in (self._block_sub, self._want_token) if e]
            subs += [b[1] for b in self._retired_blocks]
            self._subs, self._retired, self._retired_blocks = {}, [], []
            self._block_sub = self._want_token = None
            self._block = None
        for sub in subs:
            with contextlib.suppress(Exception):
                sub.undeclare()


def _err_text(reply: zenoh.Reply) -> str:
    err = reply.err
    if err is None:
        return "error reply"
    try:
        return err.payload.to_string()
    except Exception:  # noqa: BLE001
        return "error reply"


def _guarded(callback: Callable[..., None], *args: Any) -> None:
    try:
        callback(*args)
    except Exception:  # noqa: BLE001 - a subscriber bug must not kill Zenoh's thread
        log.exception("subscriber callback failed")
