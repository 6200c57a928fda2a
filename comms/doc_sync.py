"""Following a signed, versioned fleet document on the mesh: `DocSync`, for any `SignedDoc`.

Two documents are followed this way: the roster (trust/roster_sync.py `RosterSync`: a
revocation reaches every keyed member within a second) and the fleet plan (comms/plan_sync.py).
A follower

- applies a newer document pushed on its key (`covey keygen push`, `covey plan push`) at once;
- answers queries: `<key>?have=<v>` gets an answer only from members that hold a newer version
  than v, so a pull costs nothing on the wire while the fleet agrees;
- pulls (queries with its own version) at start, on every new Zenoh link (a router coming back,
  a peer joining) and again a second later, and periodically: every `pull_every_s` (jittered),
  stretched as the fleet grows so that each member hears about `pulls_heard_per_s` of the
  fleet's pulls a second (`pull_period_s`), so a member that was away, rebooted from an old file
  or missed the push catches up by itself, or on hearing a pull that holds a newer version;
- re-publishes its document when it sees an authentic older one put on the key (a member that
  is behind), after a random delay within `republish_delay_max_s`, cancelled if another member
  says the same first, and at most once per `republish_min_interval_s`: a fleet answers one stale
  document with about one re-publish, not one per member.

What arrives is checked cheapest first (`offer`), so that a flood of forged documents costs each
receiver almost nothing and never delays a real one: the size and the fixed header
(`SignedDoc.peek`) in O(1); anything not newer than the version held is dropped there,
undecoded and unverified; a newer one is verified (`SignedDoc.genuine`: the signature, about
1 ms for the largest roster) before it is decoded and applied. Refusals are counted per cause
and reported at most once per second per cause (`on_summary`, which the agent publishes as a
SECURITY event): a flood becomes a few lines, never one event per message.

The signature checks live with the documents (trust/), so this module needs no key.
"""

from __future__ import annotations

import enum
import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

import zenoh

from comms import keys
from comms.gate import Summaries
from comms.schema import DecodeError, Roster

log = logging.getLogger(__name__)

HAVE = "have"
"""The query parameter that carries the querier's roster version (`roster?have=7`)."""


@dataclass(frozen=True)
class RosterSyncConfig:
    """How a keyed member follows the roster."""

    pull_every_s: float = 5.0
    """Ask the mesh for a newer roster this often at most (each period jittered by +-20 %), and
    every `max_pull_every_s` at least. A pull is answered only by members that hold a newer
    roster, but it is delivered to every member's queryable, so a fleet of n members whose each
    pulled every 5 s would make each member hear n / 5 queries a second (40 agents: 8 a
    document, 3.8 ms of CPU a second per agent, two thirds of an idle agent's): the period
    stretches with the fleet (`pull_period_s`)."""
    pulls_heard_per_s: float = 1.0
    """The periodic pulls of the document that each member should hear a second, about: each
    member stretches its period to the fleet's pullers (estimated from the queries it hears:
    `pull_period_s`) over this. A member that fell behind learns it from the first pull it hears
    with a newer version (about 1 / this seconds) and pulls at once (`_on_query`)."""
    max_pull_every_s: float = 60.0
    """The longest periodic pull period, however many queries are heard (a flood of queries
    cannot stop a member's own pulls)."""
    reconnect_pull_s: float = 1.0
    """After a new Zenoh link (a router back, a peer joining), pull at once and again this much
    later: declarations may still be travelling when the link opens."""
    republish_min_interval_s: float = 1.0
    """At most one re-publish of this member's roster per this many seconds."""
    republish_delay_max_s: float = 0.5
    """A member that sees an authentic older roster re-publishes its own after a random delay up
    to this long, unless another member re-published it first (suppression: one answer from the
    fleet, not one from every member)."""
    answer_timeout_s: float = 2.0
    """How long a pull waits for answers."""
    summary_period_s: float = 1.0
    """At most one refusal line per cause per this many seconds."""

    def __post_init__(self) -> None:
        for name, lo, hi in (
            ("pull_every_s", 0.1, 3600.0),
            ("pulls_heard_per_s", 0.01, 100.0),
            ("max_pull_every_s", 0.1, 3600.0),
            ("reconnect_pull_s", 0.0, 60.0),
            ("republish_min_interval_s", 0.0, 3600.0),
            ("republish_delay_max_s", 0.0, 60.0),
            ("answer_timeout_s", 0.1, 60.0),
            ("summary_period_s", 0.0, 3600.0),
        ):
            value = getattr(self, name)
            if not lo <= value <= hi:
                raise ValueError(f"{name}={value} must be within [{lo:g}, {hi:g}]")
        if self.max_pull_every_s < self.pull_every_s:
            raise ValueError(
                f"max_pull_every_s={self.max_pull_every_s} must be at least "
                f"pull_every_s={self.pull_every_s}"
            )


def pull_period_s(heard: int, window_s: float, period_s: float, cfg: RosterSyncConfig) -> float:
    """The next periodic pull period of a member that heard `heard` pulls of the document (its
    own included) in the last `window_s` while it pulled every `period_s`: the fleet's pullers
    over `cfg.pulls_heard_per_s`, within [pull_every_s, max_pull_every_s]. Every member follows
    this rule, so each pulls about as often as this one: the pullers are about the pulls heard
    a second times `period_s` (RTCP scales its report interval with the members it hears
    alike, RFC 3550 6.2). A fleet of n that starts together settles at n / pulls_heard_per_s.
    What the rule holds is the pulls each member hears: about pulls_heard_per_s a second,
    however large the fleet, so the fleet's pull traffic grows with n, not n^2 (members that
    join later may keep shorter periods, which the others make up for), until every period
    is max_pull_every_s (beyond n = max_pull_every_s x pulls_heard_per_s, 60 by default, each
    hears n / max_pull_every_s)."""
    if not (window_s > 0.0 and heard >= 0):
        return min(max(period_s, cfg.pull_every_s), cfg.max_pull_every_s)
    pullers = heard / window_s * period_s
    return min(max(pullers / cfg.pulls_heard_per_s, cfg.pull_every_s), cfg.max_pull_every_s)


class Offer(enum.Enum):
    """What `DocSync.offer` made of a document."""

    APPLIED = "applied"
    SAME = "same"
    """The version held: dropped unverified."""
    OLDER = "older"
    """Older than the one held: dropped (and maybe answered with a re-publish)."""
    REFUSED = "refused"


class DocHead(Protocol):
    """What a document's O(1) header peek gives: enough to drop it or verify it."""

    @property
    def fleet(self) -> str: ...

    @property
    def version(self) -> int: ...


H = TypeVar("H", bound=DocHead)
"""A document's header type (RosterHead, PlanHead)."""
D = TypeVar("D", covariant=True)
"""A document's type (Roster, FleetPlan)."""


class SignedDoc(Protocol[H, D]):
    """One kind of signed, versioned fleet document that `DocSync` follows (the roster, the
    plan): it says where it lives, reads a header cheaply, checks a signature, applies."""

    name: str
    """What it is called in counts, logs and refusals ("roster", "plan")."""
    key: str
    """Its Zenoh key (comms/keys.py)."""

    def peek(self, data: bytes) -> H:
        """The header in O(1); raises DecodeError."""
        ...

    def held_version(self) -> int:
        """The version held now (0: none)."""
        ...

    def genuine(self, head: H) -> str | None:
        """None if the header's signature is a signer's this member trusts, else why not."""
        ...

    def apply(self, data: bytes, head: H) -> tuple[D, str | None]:
        """Decode and apply a genuine newer document: (the document, None) or (the document,
        why it was not applied); raises DecodeError."""
        ...

    def held_bytes(self) -> bytes | None:
        """The held document's wire bytes (None: none held, nothing to answer with)."""
        ...


class DocSync(Generic[H, D]):
    """One member's follower of a `SignedDoc` on an open Zenoh session (see the module
    docstring). `undeclare()` stops it."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        doc: SignedDoc[H, D],
        cfg: RosterSyncConfig = RosterSyncConfig(),
        *,
        on_summary: Callable[[str], None] | None = None,
        on_applied: Callable[[D], None] | None = None,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        rng: random.Random | None = None,
    ) -> None:
        """`on_summary(line)`: refusal summaries. `on_applied(doc)`: after a newer document was
        applied. `mono_ns`: a monotonic clock; `rng`: jitter and suppression delays."""
        self.session = session
        self.fleet = fleet
        self.doc = doc
        self.cfg = cfg
        self.key = doc.key
        self._on_applied = on_applied
        self._mono_ns = mono_ns
        self._rng = rng if rng is not None else random.Random()
        self._summaries = Summaries(on_summary, cfg.summary_period_s)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = False
        self._counts: dict[str, int] = {}
        now = mono_ns()
        self._next_pull_ns = now  # the first pull at once
        self._last_pull_ns = now - _s_ns(60.0)
        self._period_s = cfg.pull_every_s  # the periodic pull's period (`pull_period_s`)
        self._heard = 0  # pulls of the document heard since `_window_ns`
        self._window_ns = now
        self._followup_ns: int | None = None
        self._republish_ns: int | None = None
        self._last_republish_ns = now - _s_ns(3600.0)
        self._last_behind_ns = now - _s_ns(3600.0)
        self._entities: list[Any] = []
        try:
            self._entities.append(session.declare_subscriber(self.key, self._on_sample))
            self._entities.append(session.declare_queryable(self.key, self._on_query))
            self._entities.append(
                session.info.declare_transport_events_listener(self._on_link, history=False)
            )
        except BaseException:
            self.undeclare()
            raise
        self._thread = threading.Thread(target=self._run, name=f"{doc.name}-sync", daemon=True)
        self._thread.start()

    # -- what arrives ---------------------------------------------------------------------------
    def offer(self, data: bytes) -> Offer:
        """Check one document's wire bytes, cheapest first, and apply it if it is newer and
        genuine. Never raises; refusals are counted and summarised."""
        now = self._mono_ns()
        try:
            head = self.doc.peek(data)
        except DecodeError as exc:
            return self._refuse("malformed", now, str(exc))
        if head.fleet != self.fleet:
            return self._refuse("other fleet", now, f"a {self.doc.name} for fleet {head.fleet!r}")
        held = self.doc.held_version()
        if head.version == held:
            with self._lock:
                self._republish_ns = None  # another member said it first
            self._count("same")
            return Offer.SAME
        if head.version < held:
            self._count("older")
            self._behind(head, now)
            return Offer.OLDER
        forged = self.doc.genuine(head)
        if forged is not None:
            return self._refuse("forged", now, f"v{head.version}: {forged}")
        try:
            applied, problem = self.doc.apply(data, head)
        except DecodeError as exc:  # genuinely signed, yet invalid: say so
            return self._refuse("malformed", now, f"v{head.version}: {exc}")
        if problem:
            if head.version <= self.doc.held_version():
                self._count("same")  # another thread applied it (or a newer one) just now
                return Offer.SAME
            return self._refuse("refused", now, problem)
        self._count("applied")
        if self._on_applied is not None:
            try:
                self._on_applied(applied)
            except Exception:  # noqa: BLE001 - a listener bug must not undo an applied document
                log.exception("on_applied listener failed")
        return Offer.APPLIED

    def counts(self) -> dict[str, int]:
        """How many documents were applied, same, older, refused per cause ("refused: forged"),
        how many pulls, answers and re-publishes; a snapshot."""
        with self._lock:
            return dict(self._counts)

    def request_pull(self, delay_s: float = 0.0) -> None:
        """Pull within `delay_s` (a little later if one just went out)."""
        now = self._mono_ns()
        with self._lock:
            due = max(now + _s_ns(delay_s), self._last_pull_ns + _s_ns(MIN_PULL_GAP_S))
            self._next_pull_ns = min(self._next_pull_ns, due)
        self._wake.set()

    def pull_now(self, timeout_s: float = 1.0) -> None:
        """Pull once and wait for the answers, at most `timeout_s` (Zenoh ends the wait as soon
        as every member's queryable has answered or declined): a process that starts holds the
        fleet's newest document before it answers anything that depends on it."""
        replies = self.session.get(
            f"{self.key}?{HAVE}={self.doc.held_version()}",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout_s,
        )
        self._count("pulls")
        for reply in replies:
            self._on_reply(reply)

    def _behind(self, head: H, now: int) -> None:
        """An older document was put on the key: a member is behind. Re-publish ours (once,
        soon, unless someone else does), if that older one is authentic: a forged one must not
        make the fleet answer (an amplifier), and only one is verified per interval."""
        with self._lock:
            if (
                self._republish_ns is not None
                or now - self._last_republish_ns < _s_ns(self.cfg.republish_min_interval_s)
                or now - self._last_behind_ns < _s_ns(self.cfg.republish_min_interval_s)
            ):
                return
            self._last_behind_ns = now
        forged = self.doc.genuine(head)
        if forged is not None:
            self._refuse("forged", now, f"v{head.version}: {forged}")
            return
        delay_ns = _s_ns(self._rng.uniform(0.0, self.cfg.republish_delay_max_s))
        with self._lock:
            self._republish_ns = now + delay_ns
        self._wake.set()

    def _refuse(self, cause: str, now: int, why: str) -> Offer:
        self._count(f"refused: {cause}")
        self._summaries.note(
            cause,
            now,
            lambda n: (
                f"refused a {self.doc.name} ({cause}): {why}"
                if n == 1
                else f"refused {n} {self.doc.name}s ({cause}) in the last second; latest: {why}"
            ),
        )
        return Offer.REFUSED

    def _count(self, what: str, n: int = 1) -> None:
        with self._lock:
            self._counts[what] = self._counts.get(what, 0) + n

    # -- Zenoh callbacks (never raise) ----------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.offer(sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - one bad message never kills a process
            log.exception("%s offer failed", self.doc.name)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        try:
            if reply.ok is not None:
                self.offer(reply.ok.payload.to_bytes())
        except Exception:  # noqa: BLE001
            log.exception("%s offer failed", self.doc.name)

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            self._heard += 1
        try:
            have = _have(query)
            held = self.doc.held_version()
            if have is not None and have >= held:
                if have > held:  # the querier is ahead of us: catch up
                    self.request_pull()
                return
            data = self.doc.held_bytes()
            if data is None:
                return
            query.reply(self.key, data)
            self._count("answered")
        except Exception as exc:  # noqa: BLE001 - the querier may be gone
            log.debug("could not answer a %s query: %s", self.doc.name, exc)

    def _on_link(self, event: Any) -> None:
        try:
            if event.kind == zenoh.SampleKind.PUT:
                with self._lock:
                    self._followup_ns = self._mono_ns() + _s_ns(self.cfg.reconnect_pull_s)
                self.request_pull()
        except Exception:  # noqa: BLE001
            log.exception("%s link event failed", self.doc.name)

    # -- the sync thread ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            now = self._mono_ns()
            with self._lock:
                due = [self._next_pull_ns]
                due += [t for t in (self._republish_ns, self._followup_ns) if t is not None]
            self._wake.wait(max(0.0, (min(due) - now) / 1e9))
            self._wake.clear()
            if self._closed:
                return
            try:
                self._step(self._mono_ns())
            except Exception as exc:  # noqa: BLE001 - the session may be closing
                if self._closed or self.session.is_closed():  # closed under us: nothing to do
                    return
                log.warning("%s sync: %s", self.doc.name, exc)
                self._wake.wait(0.5)

    def _step(self, now: int) -> None:
        with self._lock:
            republish = self._republish_ns is not None and now >= self._republish_ns
            if republish:
                self._republish_ns = None
                self._last_republish_ns = now
            if self._followup_ns is not None and now >= self._followup_ns:
                self._followup_ns = None
                self._next_pull_ns = min(self._next_pull_ns, now)
            pull = now >= self._next_pull_ns
            if pull:
                self._last_pull_ns = now
                window_s = (now - self._window_ns) / 1e9
                if window_s >= self.cfg.pull_every_s:  # short windows (a new link's pulls) add up
                    self._period_s = pull_period_s(self._heard, window_s, self._period_s, self.cfg)
                    self._heard, self._window_ns = 0, now
                jitter = self._rng.uniform(0.8, 1.2)
                self._next_pull_ns = now + _s_ns(self._period_s * jitter)
        if republish:
            data = self.doc.held_bytes()
            if data is not None:
                publish_doc(self.session, self.key, data)
                self._count("republished")
        if pull:
            self.session.get(
                f"{self.key}?{HAVE}={self.doc.held_version()}",
                self._on_reply,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=self.cfg.answer_timeout_s,
            )
            self._count("pulls")

    def undeclare(self) -> None:
        """Stop the thread and undeclare the subscriber, queryable and link listener."""
        self._closed = True
        self._wake.set()
        thread = getattr(self, "_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        entities, self._entities = self._entities, []
        for ent in reversed(entities):
            try:
                ent.undeclare()
            except Exception:  # noqa: BLE001 - closing the session frees it anyway
                pass


MIN_PULL_GAP_S = 0.2
"""Two pulls are at least this far apart (a burst of new links makes one pull, not many)."""


def _s_ns(seconds: float) -> int:
    return int(seconds * 1e9)


def _have(query: zenoh.Query) -> int | None:
    """The querier's version from `?have=<v>`, or None (no parameter, or not a number:
    answered as a plain query)."""
    try:
        raw = query.parameters.get(HAVE)
    except Exception:  # noqa: BLE001
        return None
    if raw is None or not raw.isdigit() or len(raw) > 10:
        return None
    return int(raw)


def publish(session: zenoh.Session, fleet: str, data: bytes) -> None:
    """Put a roster's bytes on the fleet's roster key (`publish_doc`)."""
    publish_doc(session, keys.roster(fleet), data)


def publish_doc(session: zenoh.Session, key: str, data: bytes) -> None:
    """Put a document's bytes on its key, never dropped on a full queue (Zenoh's default for
    puts): a revocation must get through a flood, so it waits for room, and goes ahead of
    telemetry."""
    session.put(
        key,
        data,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=zenoh.Priority.INTERACTIVE_HIGH,
    )


@dataclass(frozen=True)
class Confirmation:
    """A member's answer to the pusher: which version of the document it holds."""

    replier: str
    """The answering session's Zenoh id (one per process)."""
    version: int


def confirmations(
    session: zenoh.Session,
    fleet: str,
    version: int,
    timeout_s: float = 1.0,
    *,
    key: str | None = None,
    peek: Callable[[bytes], DocHead] = Roster.peek,
) -> list[Confirmation]:
    """Ask the fleet who holds roster `version` or newer (the pusher's check that a push was
    heard): one query `roster?have=<version - 1>`, so only such members answer. Answers that are
    not a roster's header are skipped; signatures are not checked (the pusher only reports).
    Another document: its `key` and header `peek` (the plan: keys.plan, PlanMessage.peek)."""
    out = []
    replies = session.get(
        f"{key or keys.roster(fleet)}?{HAVE}={version - 1}",
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            head = peek(reply.ok.payload.to_bytes())
        except DecodeError:
            continue
        if head.fleet == fleet and head.version >= version:
            who = reply.replier_id
            out.append(Confirmation(str(who.zid) if who is not None else "?", head.version))
    return out
