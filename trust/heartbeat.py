"""Station heartbeats: the signed sign of life that the station-lost failsafe trusts, and the
clock offset that every member estimates from it.

A ground station (`covey gcs`) publishes a `StationHeartbeat` every `period_s` (2 Hz) on
`covey/<fleet>/gcs/<id>/heartbeat`, signed with its station key in keyed mode
(`HeartbeatPublisher`). A member (`StationHeartbeats`) checks each one, cheapest first:

    1. on its own station's key, signed at all (keyed)     else MISADDRESSED / UNSIGNED
    2. stamp newer than that station's last accepted one   else REPLAYED / OUT_OF_ORDER
    3. a station of the current roster signed it           else UNKNOWN / FORGED (keyed)

and keeps, per station (roster stations only in keyed mode; at most `max_stations` in open
mode), the last accepted stamp and the receive time of the last *fresh* one: a heartbeat is
fresh when its stamp is within `max_skew_s` (FleetAuth's freshness window, 5 s) of this member's
clock. A station is on the mesh while its last fresh heartbeat is younger than `alive_s`; the
failsafe counts `gcs_lost_hold_s` from then. Liveliness tokens (comms/presence.py) are not
signed, so in keyed mode they count for nothing here; in open mode (no keys: anyone can command
anyway) unsigned heartbeats are accepted and a station's token still keeps it on the mesh, so
that stations and tools without heartbeats keep working.

Clock offset: every accepted heartbeat, fresh or not, gives one sample
    offset = local receive time - heartbeat stamp     (this member's clock minus the station's)
which also holds the one-way latency (below a few ms on a LAN, tens of ms on a busy radio: well
inside the 5 s window). The estimate is the median of the station's last `offset_samples`, so
one delayed heartbeat does not move it. A member whose offset exceeds `max_skew_s` cannot be
heard (its states and events are stale to everyone) and cannot be commanded (every command is
stale to it): it refuses take-off saying so (`takeoff_problem`), names the offset in a stale
command's refusal (FleetAuth.clock_note), and reports it as a signed ClockReport event stamped
in the station's time, so that the station can show it (`clock_report`). It never corrects its
own clock from heartbeats: a replayed recording would then move it.
"""

from __future__ import annotations

import logging
import math
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from comms import keys
from comms.gate import Summaries
from comms.schema import ClockReport, DecodeError, Role, StationHeartbeat

log = logging.getLogger(__name__)

NO_STATION = (
    "no ground station on the mesh; the failsafe would hold: start covey gcs or --no-gcs-failsafe"
)
"""Why a vehicle with the station-lost failsafe on refuses a take-off without a station (a
command ack's reason holds 96 bytes)."""


@dataclass(frozen=True)
class HeartbeatConfig:
    """How often stations beat, and how members judge the beats."""

    period_s: float = 0.5
    """A station publishes one heartbeat every this many seconds."""
    alive_s: float = 0.75
    """A station is on the mesh while its last fresh, accepted heartbeat is younger than this
    (one and a half periods: one late heartbeat is not a loss)."""
    max_skew_s: float = 5.0
    """A heartbeat stamped further than this from the member's clock keeps no station alive;
    a keyed member uses its FleetAuth's window (the one its commands and states are held to)."""
    offset_samples: int = 9
    """The clock offset is the median of the offsets of a station's last so many heartbeats."""
    offset_expire_s: float = 60.0
    """An offset estimate is forgotten this long after its station's last heartbeat."""
    warn_offset_s: float = 1.0
    """A clock offset beyond this is reported (ClockReport), beyond `max_skew_s` as an error."""
    report_period_s: float = 5.0
    """A clock report is repeated this often while the offset stays beyond `warn_offset_s`."""
    max_stations: int = 64
    """The most stations tracked; in open mode their ids come unverified from the network."""
    summary_period_s: float = 1.0
    """At most one line per refusal cause per this many seconds."""

    def __post_init__(self) -> None:
        for name in (
            "period_s",
            "alive_s",
            "max_skew_s",
            "offset_expire_s",
            "warn_offset_s",
            "report_period_s",
            "summary_period_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value <= 3600.0):
                raise ValueError(f"{name}={value} must be within (0, 3600]")
        if self.alive_s < self.period_s:
            raise ValueError(f"alive_s={self.alive_s} must be at least period_s={self.period_s}")
        if not 1 <= self.offset_samples <= 1000:
            raise ValueError(f"offset_samples={self.offset_samples} must be within 1..1000")
        if not 1 <= self.max_stations <= 65000:
            raise ValueError(f"max_stations={self.max_stations} must be within 1..65000")


class HeartbeatPublisher:
    """A station's heartbeats, `cfg.period_s` apart on a thread, signed with the mesh's key
    (keyed mode). Use it as a context manager; `beat()` sends one at once."""

    def __init__(self, mesh: Any, gcs_id: int, cfg: HeartbeatConfig = HeartbeatConfig()) -> None:
        auth = mesh.auth
        if auth is not None and (auth.role is not Role.STATION or auth.member_id != gcs_id):
            raise ValueError(
                f"station {gcs_id}'s heartbeats need station {gcs_id}'s key, not {auth.key.name}'s"
            )
        self.mesh, self.gcs_id, self.cfg = mesh, keys.check_vehicle_id(gcs_id), cfg
        self.seq = 0
        self._lock = threading.Lock()
        self._key = keys.gcs_heartbeat(mesh.fleet, gcs_id)
        # A member that just joined asks at once (StationHeartbeats), rather than wait for the
        # next beat: a take-off right after an agent starts is not refused for want of one.
        self._queryable = mesh.session.declare_queryable(self._key, self._on_query)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{gcs_id}", daemon=True)
        self._thread.start()

    def _next(self) -> StationHeartbeat:
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        hb = StationHeartbeat(self.gcs_id, self.seq, self.mesh.clock_ns())
        return hb if self.mesh.auth is None else self.mesh.auth.sign_heartbeat(hb)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            with self._lock:
                query.reply(self._key, self._next().encode())
        except Exception as exc:  # noqa: BLE001 - the querier may be gone
            log.debug("could not answer a heartbeat query: %s", exc)

    def beat(self) -> StationHeartbeat:
        """Publish the next heartbeat now; returns it (signed in keyed mode)."""
        with self._lock:  # the thread, a caller, a query: seq and stamp rise in the order sent
            hb = self._next()
            # A put, not a declared publisher: a client's publisher declared before the
            # subscribers of members behind other routers existed never reached them (covey
            # router chains, zenoh 1.10); a put is routed each time.
            self.mesh.session.put(
                self._key,
                hb.encode(),
                congestion_control=zenoh.CongestionControl.DROP,
                express=True,
            )
        return hb

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.beat()
            except Exception as exc:  # noqa: BLE001 - a closing session must not crash the thread
                if self._stop.is_set() or _closed(self.mesh):
                    return  # the mesh went first: nothing left to beat on
                log.warning("station %d: heartbeat not sent: %s", self.gcs_id, exc)
            self._stop.wait(self.cfg.period_s)

    def close(self) -> None:
        """Stop beating (members see the station lost `alive_s` after the last beat)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        try:
            self._queryable.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass

    def __enter__(self) -> HeartbeatPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class _Station:
    """What a member keeps about one station (guarded by the receiver's lock)."""

    stamp_ns: int
    """Stamp of its last accepted heartbeat (the order check)."""
    heard_s: float
    """Local time of its last accepted heartbeat."""
    fresh_s: float = -math.inf
    """Local time of its last accepted heartbeat stamped within the freshness window."""
    offsets_s: deque[float] = field(default_factory=deque)


@dataclass(frozen=True)
class ClockOffset:
    """This member's clock against one station's, from that station's heartbeats."""

    offset_s: float
    """This member's clock minus the station's (median of the last samples), in seconds."""
    gcs_id: int
    samples: int


class StationHeartbeats:
    """What a member knows of the ground stations: which are on the mesh (verified, fresh
    heartbeats) and its clock's offset to them. Thread-safe; its subscription lives with the
    mesh's session (`close` ends it sooner).

    `clock_s`: the local monotonic clock the failsafe ticks on; receive stamps for the offset
    are the mesh's wall clock (`mesh.clock_ns`). `on_summary(line)`: one line per refusal cause
    per second (the agent publishes them as SECURITY events)."""

    def __init__(
        self,
        mesh: Any,
        cfg: HeartbeatConfig = HeartbeatConfig(),
        *,
        clock_s: Callable[[], float] = time.monotonic,
        on_summary: Callable[[str], None] | None = None,
        subscribe: bool = True,
        tokens: bool = True,
    ) -> None:
        """`subscribe=False`: no subscription (feed it with `offer`; tests). `tokens=False`:
        no liveliness fallback in open mode either (a process that does not ask `alive`)."""
        self.cfg = cfg
        self.auth = mesh.auth
        self.fleet = mesh.fleet
        self.clock_ns: Callable[[], int] = mesh.clock_ns
        self.clock_s = clock_s
        skew_s = cfg.max_skew_s if self.auth is None else self.auth.max_skew_ns / 1e9
        self.max_skew_s = skew_s
        self._skew_ns = int(skew_s * 1e9)
        self._lock = threading.Lock()
        self._stations: dict[int, _Station] = {}
        self._summaries = Summaries(on_summary or _log_summary, cfg.summary_period_s)
        self.accepted = 0
        self.refused: dict[str, int] = {}
        """Refused heartbeats per cause since start (read only)."""
        self._reported: tuple[bool, float] = (False, -math.inf)  # (a problem was told, when)
        self._sub = None
        self.tokens = None
        """Open mode only: the stations' liveliness tokens (comms/presence.py), a fallback."""
        if subscribe:
            if self.auth is None and tokens:
                self.tokens = mesh.presence()
            key = keys.all_gcs_heartbeats(self.fleet)
            self._sub = mesh.session.declare_subscriber(key, self._on_sample)
            # Ask the stations now (HeartbeatPublisher answers with a fresh heartbeat): a
            # member that just started knows its stations in a round trip, not a period.
            mesh.session.get(key, self._on_reply, target=zenoh.QueryTarget.ALL, timeout=2.0)

    def close(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closed already
                pass

    def __enter__(self) -> StationHeartbeats:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- receiving (Zenoh thread) ----------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.receive(str(sample.key_expr), sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - one bad message never kills Zenoh's thread
            log.exception("heartbeat handling failed")

    def _on_reply(self, reply: zenoh.Reply) -> None:
        try:
            if reply.ok is not None:
                self.receive(str(reply.ok.key_expr), reply.ok.payload.to_bytes())
        except Exception:  # noqa: BLE001 - one bad reply never kills Zenoh's thread
            log.exception("heartbeat reply handling failed")

    def receive(self, key: str, payload: bytes) -> str | None:
        """Decode and `offer` one heartbeat that arrived on `key` now; the refusal or None."""
        recv_ns, now_s = self.clock_ns(), self.clock_s()
        parsed = keys.parse_gcs_heartbeat_key(key)
        try:
            hb = StationHeartbeat.decode(payload)
        except DecodeError as exc:
            return self._refuse("malformed", 0, str(exc), recv_ns)
        if parsed is None or parsed[0] != self.fleet or parsed[1] != hb.gcs_id:
            return self._refuse("misaddressed", hb.gcs_id, f"arrived on {key}", recv_ns)
        return self.offer(hb, recv_ns, now_s)

    def offer(self, hb: StationHeartbeat, recv_ns: int, now_s: float) -> str | None:
        """Check one heartbeat received at `recv_ns` (wall) / `now_s` (monotonic): None if
        accepted, else the refusal cause (counted, summarised)."""
        sid = hb.gcs_id
        if self.auth is not None and not hb.sig:
            return self._refuse("unsigned", sid, "no signature", recv_ns)
        with self._lock:
            st = self._stations.get(sid)
            known = len(self._stations)
        if st is not None and hb.stamp_ns <= st.stamp_ns:
            cause = "replayed" if hb.stamp_ns == st.stamp_ns else "out of order"
            return self._refuse(cause, sid, f"seq {hb.seq}", recv_ns)
        if self.auth is not None:
            problem = self.auth.check_heartbeat(hb)
            if problem:
                cause = "unknown signer" if problem.startswith("unknown") else "forged"
                return self._refuse(cause, sid, problem, recv_ns)
        elif st is None and known >= self.cfg.max_stations:
            return self._refuse("too many stations", sid, "table full", recv_ns)
        fresh = abs(recv_ns - hb.stamp_ns) <= self._skew_ns
        with self._lock:
            st = self._stations.get(sid)
            if st is not None and hb.stamp_ns <= st.stamp_ns:  # a newer one won the race
                cause = "out of order"
            else:
                if st is None:
                    st = self._stations[sid] = _Station(hb.stamp_ns, now_s)
                st.stamp_ns, st.heard_s = hb.stamp_ns, now_s
                if fresh:
                    st.fresh_s = now_s
                st.offsets_s.append((recv_ns - hb.stamp_ns) / 1e9)
                while len(st.offsets_s) > self.cfg.offset_samples:
                    st.offsets_s.popleft()
                self.accepted += 1
                return None
        return self._refuse(cause, sid, f"seq {hb.seq}", recv_ns)

    def _refuse(self, cause: str, sid: int, detail: str, recv_ns: int) -> str:
        with self._lock:
            self.refused[cause] = self.refused.get(cause, 0) + 1
        self._summaries.note(
            cause,
            recv_ns,
            lambda n: (
                f"refused {n} {cause} station heartbeat{'s' if n > 1 else ''} "
                f"(latest claims station {sid}: {detail})"
            ),
        )
        return cause

    # -- what the shells ask -------------------------------------------------------------
    def _counts(self, sid: int) -> bool:
        """A station whose heartbeats count now: in keyed mode still in the roster."""
        return self.auth is None or self.auth.is_member(Role.STATION, sid)

    def stations(self, now_s: float) -> set[int]:
        """The stations on the mesh: a fresh, accepted heartbeat younger than `alive_s`."""
        with self._lock:
            live = {
                sid for sid, st in self._stations.items() if now_s - st.fresh_s < self.cfg.alive_s
            }
        return {sid for sid in live if self._counts(sid)}

    def alive(self, now_s: float) -> bool:
        """Whether a ground station is on the mesh (what the station-lost failsafe asks). Open
        mode: also a station's liveliness token (stations and tools without heartbeats)."""
        if self.stations(now_s):
            return True
        return self.tokens is not None and bool(self.tokens.ground_stations)

    def offset(self, now_s: float) -> ClockOffset | None:
        """This member's clock against the station heard from last, or None if none was heard
        within `offset_expire_s`."""
        with self._lock:
            heard = [
                (st.heard_s, sid, list(st.offsets_s))
                for sid, st in self._stations.items()
                if st.offsets_s and now_s - st.heard_s <= self.cfg.offset_expire_s
            ]
        heard = [h for h in heard if self._counts(h[1])]
        if not heard:
            return None
        _, sid, samples = max(heard)
        return ClockOffset(statistics.median(samples), sid, len(samples))

    def clock_problem(self, now_s: float | None = None) -> str | None:
        """Why this member's clock rules out flying (its offset to a station exceeds the
        freshness window), or None. Also FleetAuth.clock_note, for stale-command refusals."""
        off = self.offset(self.clock_s() if now_s is None else now_s)
        if off is None or abs(off.offset_s) <= self.max_skew_s:
            return None
        return (
            f"vehicle clock {off.offset_s:+.1f} s against station {off.gcs_id} "
            f"(limit {self.max_skew_s:g} s): set its time (NTP or GPS)"
        )

    def takeoff_problem(self, now_s: float, require_gcs: bool) -> str | None:
        """Why a take-off is refused now, or None: a clock off by more than the freshness
        window; with the station-lost failsafe on (`require_gcs`), no station on the mesh (the
        failsafe would hold the vehicle as soon as it climbed)."""
        problem = self.clock_problem(now_s)
        if problem:
            return problem
        if require_gcs and not self.alive(now_s):
            return NO_STATION
        return None

    def clock_reports(
        self, now_s: float, vehicle_ids: Iterable[int]
    ) -> list[tuple[ClockReport, int]]:
        """The ClockReports due now, one per vehicle of this process (they share its clock),
        each with the stamp to put on its event: the station's time, since a vehicle whose clock
        is off would otherwise be stale to the station that must show it. Due when the offset
        first exceeds `warn_offset_s`, every `report_period_s` while it does, and once when it
        is back within it; else none."""
        off = self.offset(now_s)
        if off is None:
            return []
        bad = abs(off.offset_s) > self.cfg.warn_offset_s
        told, when_s = self._reported
        if (bad and told and now_s - when_s < self.cfg.report_period_s) or (not bad and not told):
            return []
        self._reported = (bad, now_s)
        stamp_ns = max(0, self.clock_ns() - int(off.offset_s * 1e9))
        return [
            (ClockReport(vid, off.offset_s, off.gcs_id, ok=not bad), stamp_ns)
            for vid in vehicle_ids
        ]


def _closed(mesh: Any) -> bool:
    try:
        mesh.session  # noqa: B018 - a closed Mesh raises here
    except RuntimeError:
        return True
    return False


def _log_summary(line: str) -> None:
    log.warning("SECURITY: %s", line)
