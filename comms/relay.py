"""A router's cell relay: each vehicle hears its block of cells as one message a period.

An agent hears its neighbours' states one message each, each from its own process at its own
phase. On a companion computer a message costs more in wake-ups than in work: Zenoh's threads
took 73 us a state on this machine, 1.5 ms of a 10 Hz tick with 20 neighbours
(docs/companion.md, "Round nine"). The router hears every one of those states anyway, so a
relay beside it (in the router's own process: `covey router`, the demo's embedded router)
gathers them by cell and, once a period, puts to each block that a vehicle wants the states its
cells got since the last period, in RelayBatch messages of at most 4 KiB.

    vehicle N declares   covey/<fleet>/v/N/want/<rid>/<k>/<cn>/<ce>   (a liveliness token)
    relay <rid> puts     covey/<fleet>/relay/<rid>/<k>/<cn>/<ce>      every period_s

A block is the (2k + 1)^2 cells around an anchor cell: exactly what comms/scope.py has an agent
hear. The relay subscribes only to the cells of the blocks wanted from it, so a relay adds no
traffic between routers that the agents' own subscriptions would not have made.

What a vehicle trusts does not change: the relay forwards each state's bytes as its vehicle
published them, and the vehicle checks each one as it would on its own key (signature or link
tag, order, the cell its position is in: `decode_placed`). The relay itself refuses a state
whose key names another vehicle or another cell than the state's (counted, never forwarded),
as the mesh does. A relay can withhold states, as its router can; it cannot forge one.

A relay puts a batch on every wanted block every period it heard states there, and an empty one
at least every `keepalive_s` while the block is quiet, so that a vehicle can tell a quiet block
from a relay that is not there or stopped: comms/mesh.py
CellSubscription keeps its own cell subscriptions until it has heard the relay, and takes them
up again when the relay is silent for `RELAY_SILENT_S`. A router without a relay costs a vehicle
one token and one subscriber that hear nothing. One relay serves every fleet its router routes.

The price is latency: a state waits for the relay's next period, period_s / 2 on average.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from comms import keys
from comms.feed import runs_within
from comms.schema import MAX_FEED_BYTES, DecodeError, RelayBatch, VehicleState

log = logging.getLogger(__name__)

RELAY_SILENT_S = 1.0
"""A vehicle that heard no batch from its relay for this long hears its cells itself again: more
than three of a quiet block's keep-alives (`RelayConfig.keepalive_s`)."""


class MisplacedState(DecodeError):
    """A state on another vehicle's key, or in another cell than its position's."""


def decode_placed(
    key: str, payload: bytes, block: tuple[int, keys.Cell] | None = None
) -> VehicleState:
    """The state in `payload`, checked against where it came: on a state key (`block` None), the
    key's vehicle and cell must be the state's; from a relay block (k, anchor), the state's cell
    must be within it. Raises DecodeError (MisplacedState for a state in the wrong place)."""
    state = VehicleState.decode(payload)
    cell = keys.cell_of(state.pos_ned_m)
    if block is not None:
        k, (an, ae) = block
        if max(abs(cell[0] - an), abs(cell[1] - ae)) > k:
            raise MisplacedState(
                f"state of vehicle {state.vehicle_id} in cell {cell} came in the relay block of "
                f"the cells within {k} of {(an, ae)}"
            )
        return state
    parsed = keys.parse_state_key(key)
    if parsed is None or parsed[1] != state.vehicle_id:
        raise DecodeError(f"state of vehicle {state.vehicle_id} arrived on {key}")
    if parsed[2] is not None and parsed[2] != cell:
        # A state outside its position's cell would be hidden from the neighbours that must
        # hear it: refused, whatever its signature says.
        raise MisplacedState(
            f"state of vehicle {state.vehicle_id} at N {state.pos_ned_m[0]:.1f} "
            f"E {state.pos_ned_m[1]:.1f} m is in cell {cell}, not in cell {parsed[2]} of its key"
        )
    return state


def batches(states: list[bytes], seq: int) -> list[bytes]:
    """`states` in RelayBatch messages of at most MAX_FEED_BYTES, numbered from `seq`; one empty
    batch if there are none."""
    runs = runs_within(states, len, RelayBatch.size, MAX_FEED_BYTES) or [()]
    return [RelayBatch((seq + i) & 0xFFFFFFFF, run).encode() for i, run in enumerate(runs)]


@dataclass(frozen=True)
class RelayConfig:
    """A cell relay's settings (`covey router --cell-relay-period-s`)."""

    period_s: float = 0.1
    """How often each wanted block gets its batch: a state waits half of it on average."""
    keepalive_s: float = 0.3
    """A quiet block gets an empty batch this often (a block with states gets them every
    period): how a vehicle tells a quiet block from a relay that went (`RELAY_SILENT_S`)."""
    ring: int = 4096
    """States kept per cell between two periods (the oldest dropped when full)."""
    max_wants_per_vehicle: int = 4
    """Blocks one vehicle id may want at once (an agent wants one; a second while it moves):
    more are refused, so that one member cannot make the relay subscribe the whole grid."""
    max_blocks: int = 4096
    """Blocks the relay serves at once, all vehicles together; wants beyond it are refused."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and 0.01 <= self.period_s <= 0.3):
            raise ValueError(f"period_s={self.period_s} must be within [0.01, 0.3] s")
        if not (math.isfinite(self.keepalive_s) and self.period_s <= self.keepalive_s <= 0.3):
            raise ValueError(
                f"keepalive_s={self.keepalive_s} must be within [period_s, 0.3] s: a vehicle "
                f"waits {RELAY_SILENT_S:g} s before it calls its relay gone"
            )
        if not 16 <= self.ring <= 1 << 20:
            raise ValueError(f"ring={self.ring} must be within 16..{1 << 20}")
        if not 1 <= self.max_wants_per_vehicle <= 64:
            raise ValueError(f"max_wants_per_vehicle={self.max_wants_per_vehicle}: 1..64")
        if not 1 <= self.max_blocks <= 1 << 20:
            raise ValueError(f"max_blocks={self.max_blocks} must be within 1..{1 << 20}")


@dataclass
class RelayStats:
    states_in: int = 0
    refused: int = 0
    """States (on the wrong key or cell, malformed) and wants (too many) refused."""
    batches_out: int = 0
    states_out: int = 0
    blocks: int = 0
    cells: int = 0
    last_refusal: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def bump(self, **counts: int) -> None:
        with self._lock:
            for name, n in counts.items():
                setattr(self, name, getattr(self, name) + n)


Block = tuple[str, int, keys.Cell]
"""(fleet, k, anchor cell) of a relay block."""


class CellRelay:
    """The cell relay of the router whose session this is, for every fleet it routes. Runs a
    thread that relays every `cfg.period_s` until closed; use it as a context manager.
    `flush()` does one period's work (tests call it with `start=False`)."""

    def __init__(
        self,
        session: zenoh.Session,
        cfg: RelayConfig = RelayConfig(),
        *,
        start: bool = True,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.relay_id = str(session.info.zid())
        self.stats = RelayStats()
        self._session = session
        self._clock_s = clock_s
        self._lock = threading.Lock()
        self._wants: dict[str, Block] = {}  # want token key -> block
        self._owners: dict[str, tuple[str, int]] = {}  # want token key -> (fleet, vehicle id)
        self._waiting: dict[str, tuple[Block, tuple[str, int]]] = {}  # refused, retried on room
        self._cells: dict[tuple[str, keys.Cell], Any] = {}  # (fleet, cell) -> its subscriber
        self._pubs: dict[Block, tuple[Any, int]] = {}  # block -> (publisher, next seq)
        self._sent_s: dict[Block, float] = {}  # block -> when it last got a batch
        self._stop = threading.Event()
        self._entities: list[Any] = [
            session.liveliness().declare_subscriber(
                keys.all_relay_wants(self.relay_id), self._on_want, history=True
            ),
        ]
        self._thread: threading.Thread | None = None
        if start:
            self._thread = threading.Thread(target=self._run, name="covey-relay", daemon=True)
            self._thread.start()

    def __enter__(self) -> CellRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def undeclare(self) -> None:  # as Mesh closes what it keeps
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with self._lock:
            ents = [*self._entities, *self._cells.values(), *(p for p, _ in self._pubs.values())]
            self._entities, self._cells, self._pubs = [], {}, {}
        for ent in reversed(ents):
            with contextlib.suppress(Exception):
                ent.undeclare()

    def _on_want(self, sample: zenoh.Sample) -> None:
        """A vehicle wants a block, or no longer does (its token went: it moved, or it left)."""
        key = str(sample.key_expr)
        parsed = keys.parse_relay_want(key)
        if parsed is None or parsed[2] != self.relay_id:
            self._refuse(f"a want token on {key}, which is none of this relay's")
            return
        fleet, vid = parsed[0], parsed[1]
        with self._lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self._waiting.pop(key, None)
                if self._wants.pop(key, None) is not None:
                    self._owners.pop(key, None)
                    for waiting, (block, owner) in list(self._waiting.items()):  # room now?
                        if self._admit(waiting, block, owner) is None:
                            del self._waiting[waiting]
                return
            block, owner = (fleet, parsed[3], parsed[4]), (fleet, vid)
            why = self._admit(key, block, owner)
            if why is None:
                return
            self._waiting[key] = (block, owner)
        self._refuse(f"a want on {key}: {why}")

    def _admit(self, key: str, block: Block, owner: tuple[str, int]) -> str | None:
        """Take the want `key` if the bounds allow (lock held); else why not."""
        mine = sum(1 for o in self._owners.values() if o == owner)
        if key not in self._wants and mine >= self.cfg.max_wants_per_vehicle:
            return f"vehicle {owner[1]} of fleet {owner[0]!r} already wants {mine} blocks"
        if (
            block not in self._wants.values()
            and len(set(self._wants.values())) >= self.cfg.max_blocks
        ):
            return f"the relay serves {self.cfg.max_blocks} blocks already"
        self._wants[key], self._owners[key] = block, owner
        return None

    def _refuse(self, why: str) -> None:
        self.stats.bump(refused=1)
        self.stats.last_refusal = why

    def _run(self) -> None:
        next_s = self._clock_s()
        while not self._stop.is_set():
            next_s += self.cfg.period_s
            wait_s = next_s - self._clock_s()
            if wait_s < 0:  # fell behind (a loaded machine): start again from now
                next_s, wait_s = self._clock_s(), 0.0
            if self._stop.wait(wait_s):
                return
            try:
                self.flush()
            except Exception as exc:  # one bad period never stops the relay
                log.warning("cell relay: a period failed: %s", exc)

    def flush(self) -> int:
        """One period: follow the wanted blocks, take what each cell heard, put each wanted
        block's batch(es), an empty one for a quiet block. Returns the number of batches put."""
        with self._lock:
            blocks = set(self._wants.values())
        cells = {(f, c) for f, k, a in blocks for c in keys.block_cells(k, a)}
        self._follow(blocks, cells)
        heard: dict[tuple[str, keys.Cell], list[bytes]] = {}
        for where, sub in list(self._cells.items()):
            got = heard.setdefault(where, [])
            while (sample := sub.try_recv()) is not None:
                self._take(sample, got)
        put, now_s = 0, self._clock_s()
        for block in sorted(blocks):
            pub, seq = self._pubs[block]
            fleet, k, anchor = block
            states = [s for c in keys.block_cells(k, anchor) for s in heard.get((fleet, c), ())]
            quiet_s = now_s - self._sent_s.get(block, -math.inf)
            if not states and quiet_s < self.cfg.keepalive_s - self.cfg.period_s / 2:
                continue  # quiet, and kept alive recently enough (half a period: timer jitter)
            self._sent_s[block] = now_s
            out = batches(states, seq)
            for batch in out:
                pub.put(batch)
            put += len(out)
            self._pubs[block] = (pub, (seq + len(out)) & 0xFFFFFFFF)
            self.stats.bump(states_out=len(states))
        self.stats.bump(batches_out=put)
        return put

    def _take(self, sample: zenoh.Sample, got: list[bytes]) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            decode_placed(key, payload)
        except DecodeError as exc:
            self._refuse(f"{key}: {exc}")
            return
        self.stats.bump(states_in=1)
        got.append(payload)

    def _follow(self, blocks: set[Block], cells: set[tuple[str, keys.Cell]]) -> None:
        """Subscribe to exactly `cells` and hold a publisher for exactly `blocks`."""
        gone: list[Any] = []
        for fleet, cell in cells - self._cells.keys():
            self._cells[(fleet, cell)] = self._session.declare_subscriber(
                keys.cell_states(fleet, cell), zenoh.handlers.RingChannel(self.cfg.ring)
            )
        for where in self._cells.keys() - cells:
            gone.append(self._cells.pop(where))
        for block in blocks - self._pubs.keys():
            fleet, k, anchor = block
            pub = self._session.declare_publisher(
                keys.relay_block(fleet, self.relay_id, k, anchor),
                congestion_control=zenoh.CongestionControl.DROP,
                express=True,
            )
            self._pubs[block] = (pub, 1)
        for block in self._pubs.keys() - blocks:
            gone.append(self._pubs.pop(block)[0])
            self._sent_s.pop(block, None)
        for ent in gone:
            with contextlib.suppress(Exception):
                ent.undeclare()
        self.stats.blocks, self.stats.cells = len(self._pubs), len(self._cells)
