"""Record a fleet's whole mesh into MCAP, and read recordings back (even cut-off ones).

One MCAP channel per Zenoh key, carrying the raw covey bytes (message encoding "covey-v1"; the
schema record holds the binary layout from comms.schema), log_time = receive time in ns:

    covey/<fleet>/c/<cn>/<ce>/v/<id>/state  VehicleState  (subscriber on covey/<fleet>/**)
    covey/<fleet>/msg/<id>/event  Event             (same subscriber)
    covey/<fleet>/msg/<id>/trace  GuidanceTrace     (same subscriber; agents with --trace-guidance)
    covey/<fleet>/v/*/cmd       Command             (a queryable that records and never replies)
    covey/<fleet>/v/<id>/alive  one byte, 1 = token appeared, 0 = gone (liveliness, with history)

Beside them, unless RecordConfig.foxglove is off, the same traffic in Foxglove's well-known
schemas (/tf, /scene, /vehicles/<id>/pose|fix|link, /events, /commands, /acks; see
recording/foxglove_channels.py), so that Foxglove opens the file as it is. They are made in a child
process (recording/foxglove_worker.py) from the raw chunks, off the path that receives the mesh.
Readers here skip those: `read_recording` returns only covey's own channels, so replay is
unchanged by them.

Acks are Zenoh replies that only the querier sees; the recorder cannot see them. Anything
published under covey/<fleet>/** is recorded but the stations' feed (covey/<fleet>/msg/<id>/feed,
comms/feed.py: copies of states recorded on their own keys), so an ack that its vehicle also publishes on
covey/<fleet>/msg/<id>/ack lands in the channel of that key (schema covey.CommandAck).

The file survives a SIGKILL of the recorder: chunks are small and flushed every
`flush_interval_s`, and `read_recording` streams records and stops cleanly at a torn tail
(no summary or footer needed). At most the last flush interval of covey's channels is lost;
the standard ones may lag further behind (the worker's backlog on busy cores), and
`covey record --foxglove-from` remakes them.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Protocol

import zenoh
from mcap.exceptions import EndOfFile
from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from comms import keys, schema
from comms.session import MeshConfig, open_session
from recording.foxglove_channels import FoxgloveConfig
from recording.foxglove_worker import (
    DEFER_ABOVE_HZ,
    FIRST_ID,
    MAX_DEFERRED_BYTES,
    FoxgloveChunks,
    FoxgloveWorker,
    WorkerDone,
)
from recording.mcap_chunks import MAGIC, BuiltChunk, ChunkBuilder, McapFile

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "covey-v1"
PRESENCE_ENCODING = "covey-presence-v1"
SCHEMA_ENCODING = "covey-struct"
"""Schema data is the struct layout text below: not a standard MCAP encoding, read by covey."""
_LAYOUTS = {
    "state": ("covey.VehicleState", "<BBHIQ3f3ff3fBBHf (comms/schema.py)"),
    "event": (
        "covey.Event",
        "<BBHQBB120s, or an ActionOutcome <BBHQQBB + detail; the first byte is the type "
        "(comms/schema.py)",
    ),
    "trace": ("covey.GuidanceTrace", "<BBHIQd3dBH + n*<HId (comms/schema.py)"),
    "cmd": ("covey.Command", "<BBQQHB3dIH + n*H + 32s (comms/schema.py); query payload"),
    "alive": ("covey.Presence", "1 byte: 1 = liveliness token appeared, 0 = it disappeared"),
    "ack": ("covey.CommandAck", "<BBHQQBB96s32s (comms/schema.py)"),
    "other": ("covey.Message", "any covey message; the first byte is its type (comms/schema.py)"),
}


@dataclass(frozen=True)
class RecordConfig:
    """What `covey record` records, and where."""

    path: str = "flight.mcap"
    """Output MCAP file (overwritten)."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """How to join the mesh; mesh.fleet is the fleet recorded. To lose nothing, join as a client
    of a router (`covey record` does by default): a router hands its clients a new vehicle's
    states from the first one, while a peer hears it only once their gossip link is up (Zenoh
    peers do not route for each other), which can be after its first states."""
    duration_s: float | None = None
    """Stop after this long; None = until stopped (Ctrl-C, SIGTERM or the `stop` event)."""
    flush_interval_s: float = 0.2
    """Flush a chunk to disk at least this often: what a SIGKILL can lose."""
    chunk_bytes: int = 16 * 1024
    """Close a chunk once it holds this many bytes."""
    record_commands: bool = True
    """Declare a non-replying queryable on the fleet's cmd keys to record commands."""
    foxglove: FoxgloveConfig | None = field(default_factory=FoxgloveConfig)
    """Also write Foxglove's standard channels, drawn this way; None = covey's channels only."""

    def __post_init__(self) -> None:
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration_s={self.duration_s} must be > 0")
        if not 0.01 <= self.flush_interval_s <= 60:
            raise ValueError(f"flush_interval_s={self.flush_interval_s} must be within 0.01..60")
        if not 512 <= self.chunk_bytes <= 64 * 2**20:
            raise ValueError(f"chunk_bytes={self.chunk_bytes} must be within 512..64 MiB")


def _leaf(topic: str) -> str:
    parsed = keys.parse_vehicle_key(topic)
    if parsed is not None:
        return parsed[2]
    for leaf in ("cmd", "ack"):
        if topic.endswith("/" + leaf):
            return leaf
    return "other"


class FoxgloveIncomplete(RuntimeError):
    """The file is complete and covey's channels are whole, but the Foxglove worker stopped
    early: the standard channels lack the rest (`covey record --foxglove-from` remakes them)."""


_STOP = object()


class McapSink:
    """Thread-safe MCAP writer: callbacks `put()`, one writer thread writes and flushes.

    The writer thread writes covey's raw bytes only. With `foxglove` set, at each flush it hands
    the uncompressed records of the raw chunks written since the last flush to the Foxglove
    worker (a child process, recording/foxglove_worker.py), whose finished chunks of the standard
    channels come back through the same queue and are written as they are;
    `foxglove_worker=False` converts in the writer thread instead (the reference path, and what
    an offline conversion uses)."""

    def __init__(
        self,
        out: BinaryIO,
        fleet: str,
        chunk_bytes: int,
        flush_interval_s: float,
        clock_s: Callable[[], float] = time.monotonic,
        foxglove: FoxgloveConfig | None = None,
        foxglove_worker: bool = True,
        foxglove_defer_hz: float = DEFER_ABOVE_HZ,
    ) -> None:
        self._out = out
        self._file = McapFile(out, profile="covey", library="covey-record")
        self._file.add_metadata(
            "covey", {"fleet": fleet, "schema_version": str(schema.SCHEMA_VERSION)}
        )
        self._out.flush()
        self._raw = ChunkBuilder()
        self._chunk_bytes = chunk_bytes
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, leaf)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._flush_interval_s = flush_interval_s
        self._clock_s = clock_s
        self.counts: dict[str, int] = {}
        self.foxglove_error = ""
        """Why the standard channels are incomplete (the worker died), or empty."""
        self._inline: FoxgloveChunks | None = None
        self._worker: FoxgloveWorker | None = None
        if foxglove is not None and foxglove_worker:
            self._worker = FoxgloveWorker(foxglove, self._queue.put)
        elif foxglove is not None:
            self._inline = FoxgloveChunks(foxglove)
        self._plains: list[bytes] | None = None if foxglove is None else []
        self._plain_bytes = 0
        self._defer_hz = foxglove_defer_hz
        self._since_flush = 0  # messages written since the last flush
        self._flushed_s = clock_s()
        self._thread = threading.Thread(target=self._run, name="covey-record", daemon=True)
        self._thread.start()

    def put(self, topic: str, data: bytes, recv_ns: int) -> None:
        self._queue.put((topic, data, recv_ns))

    def _channel(self, topic: str) -> tuple[int, str] | None:
        """A new topic's (channel id, leaf), or None when MCAP's u16 ids below FIRST_ID (the
        standard channels have the rest) are spent: then its messages are refused, counted in
        "refused", and said once, rather than the recording failing."""
        cid = len(self._channels) + 1
        if cid >= FIRST_ID:
            if "refused" not in self.counts:
                log.error("more than %d covey topics: refusing messages on new ones", cid - 1)
            self.counts["refused"] = self.counts.get("refused", 0) + 1
            return None
        leaf = _leaf(topic)
        name, layout = _LAYOUTS.get(leaf, _LAYOUTS["other"])
        sid = self._schemas.get(name)
        if sid is None:
            sid = self._schemas[name] = len(self._schemas) + 1
            self._raw.add_schema(Schema(sid, layout.encode(), SCHEMA_ENCODING, name))
        enc = PRESENCE_ENCODING if leaf == "alive" else MESSAGE_ENCODING
        self._raw.add_channel(Channel(cid, topic, enc, {}, sid))
        self._channels[topic] = (cid, leaf)
        return cid, leaf

    def _write(self, item: tuple[str, bytes, int]) -> None:
        topic, data, recv_ns = item
        known = self._channels.get(topic) or self._channel(topic)
        if known is None:
            return
        cid, leaf = known
        self._raw.add(cid, recv_ns, data, recv_ns)
        self._since_flush += 1
        self.counts[leaf] = self.counts.get(leaf, 0) + 1
        if self._raw.size > self._chunk_bytes:
            self._write_raw_chunk()

    def _write_raw_chunk(self) -> None:
        """Write the raw chunk; keep its records for the standard channels."""
        built = self._raw.build(keep_plain=self._plains is not None)
        if built is not None:
            self._file.write_chunk(built)
            if self._plains is not None:
                self._plains.append(built.plain)
                self._plain_bytes += len(built.plain)

    def _write_foxglove(self, built: BuiltChunk) -> None:
        self._file.write_chunk(built)
        self.counts["foxglove"] = self.counts.get("foxglove", 0) + built.messages

    def _flush(self, last: bool = False) -> None:
        """Write the raw chunk, pass what was written since the last flush on for the standard
        channels, flush the file.

        While messages arrive faster than foxglove_defer_hz, the worker is given nothing (up
        to MAX_DEFERRED_BYTES): converting beside a saturated recorder cost states even at the
        lowest priority (see DEFER_ABOVE_HZ); it catches up once the rate falls, or at close."""
        now = self._clock_s()
        rate_hz = self._since_flush / max(now - self._flushed_s, 1e-6)
        self._since_flush, self._flushed_s = 0, now
        self._write_raw_chunk()
        if self._plains and self._inline is not None:
            plains, self._plains, self._plain_bytes = self._plains, [], 0
            for chunk in self._inline.add(plains):
                self._write_foxglove(chunk)
        elif (
            self._plains
            and self._worker is not None
            and (last or rate_hz <= self._defer_hz or self._plain_bytes >= MAX_DEFERRED_BYTES)
        ):
            plains, self._plains, self._plain_bytes = self._plains, [], 0
            self._worker.send(plains)
        self._file.flush()

    def _run(self) -> None:
        get = self._queue.get
        stopping = False
        while True:
            try:
                item = get(timeout=self._flush_interval_s)
            except queue.Empty:
                item = None
            if item.__class__ is tuple:
                self._write(item)
            elif item.__class__ is BuiltChunk:
                self._write_foxglove(item)
            elif item is _STOP:
                self._flush(last=True)
                if self._inline is not None:
                    self._say_refused(self._inline.refused)
                if self._worker is None or self.foxglove_error:
                    return
                self._worker.end()  # then write its chunks until it is done
                stopping = True
                behind = self._worker.sent - self._worker.converted
                if behind > 1:  # it runs at low priority: on busy cores it lags, and we wait
                    log.info("finishing the Foxglove channels: %d flushes to convert", behind)
            elif isinstance(item, WorkerDone):
                if stopping:
                    self.foxglove_error = item.error
                    self._say_refused(item.refused)
                    return
                # Died while recording: keep recording covey's channels, and say so now.
                self.foxglove_error = item.error or "the Foxglove worker ended early"
                self._plains = None
                log.error("%s; recording covey's channels only from here", self.foxglove_error)
            if self._clock_s() - self._flushed_s >= self._flush_interval_s:
                self._flush()

    def _say_refused(self, n: int) -> None:
        if n:
            self.counts["foxglove_refused"] = n
            log.warning(
                "%d standard messages not written: more topics than Foxglove channel ids", n
            )

    def close(self) -> None:
        """Write what is queued (and the Foxglove worker's last chunks), the summary and the
        footer. Raises FoxgloveIncomplete, after finishing the file, if the worker died."""
        self._queue.put(_STOP)
        self._thread.join()
        if self._worker is not None:
            self._worker.close()
        self._worker = self._inline = self._plains = None  # after close(): covey's bytes only
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item.__class__ is tuple:
                self._write(item)
        built = self._raw.build()
        if built is not None:
            self._file.write_chunk(built)
        self._file.finish()
        self._out.flush()
        if self.foxglove_error:
            log.error("%s", self.foxglove_error)
            raise FoxgloveIncomplete(
                f"{self.foxglove_error}; covey's channels are whole, and "
                "`covey record --foxglove-from` remakes the standard ones"
            )


class Sink(Protocol):
    """Where a Recorder puts what it hears (called from Zenoh's callback threads)."""

    counts: dict[str, int]

    def put(self, topic: str, data: bytes, recv_ns: int) -> None: ...

    def close(self) -> None: ...


class Recorder:
    """Records one fleet's mesh traffic while open. Use it as a context manager."""

    def __init__(
        self,
        cfg: RecordConfig,
        clock_ns: Callable[[], int] = time.time_ns,
        sink: Sink | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        """`sink` replaces the MCAP file (cfg.path is then unused): the live Foxglove bridge is
        a recorder whose sink is a WebSocket server. `stop`: give up waiting for the router
        (a client's) once set (comms.session.open_session)."""
        self.cfg = cfg
        self._clock_ns = clock_ns
        fleet = cfg.mesh.fleet
        self._file = None if sink is not None else open(cfg.path, "wb")  # noqa: SIM115 - closed in close()
        self._entities: list = []
        try:
            if sink is not None:
                self.sink: Sink = sink
            else:
                assert self._file is not None  # opened above when no sink is given
                self.sink = McapSink(
                    self._file, fleet, cfg.chunk_bytes, cfg.flush_interval_s, foxglove=cfg.foxglove
                )
            self._session: zenoh.Session | None = open_session(cfg.mesh, stop)
            s = self._session
            self._entities.append(s.declare_subscriber(keys.everything(fleet), self._on_sample))
            self._entities.append(
                s.liveliness().declare_subscriber(
                    keys.everything(fleet), self._on_alive, history=True
                )
            )
            if cfg.record_commands:
                # complete=False: a get that asks for complete answers never routes here, and
                # this queryable never replies, so vehicles' acks are untouched.
                self._entities.append(
                    s.declare_queryable(keys.all_cmds(fleet), self._on_query, complete=False)
                )
        except Exception:
            self.close()
            raise

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            key = str(sample.key_expr)
            if key.endswith("/feed") and keys.parse_feed_key(key) is not None:
                return  # the stations' feed: copies of states recorded on their own keys
            self.sink.put(key, sample.payload.to_bytes(), self._clock_ns())

    def _on_alive(self, sample: zenoh.Sample) -> None:
        alive = b"\x01" if sample.kind == zenoh.SampleKind.PUT else b"\x00"
        self.sink.put(str(sample.key_expr), alive, self._clock_ns())

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        self.sink.put(str(query.key_expr), payload, self._clock_ns())
        # Dropping the query without a reply finalises it at once for this queryable.

    @property
    def counts(self) -> dict[str, int]:
        return dict(self.sink.counts)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for ent in reversed(self._entities):
            with contextlib.suppress(Exception):
                ent.undeclare()
        self._entities = []
        session, self._session = getattr(self, "_session", None), None
        if session is not None:
            session.close()
        if hasattr(self, "sink"):
            self.sink.close()
            del self.sink
        if self._file is not None and not self._file.closed:
            self._file.close()


def record(
    cfg: RecordConfig,
    stop: threading.Event | None = None,
    on_open: Callable[[Recorder], None] | None = None,
) -> dict[str, int]:
    """Record until cfg.duration_s passes or `stop` is set; returns message counts by kind.
    The duration bounds the whole run, a client's wait for its router included: nobody
    answering by then raises MeshUnreachable."""
    from cli.options import stop_after

    stop = stop or threading.Event()
    with stop_after(cfg.duration_s, stop), Recorder(cfg, stop=stop) as rec:
        if on_open is not None:
            on_open(rec)
        stop.wait()
        counts = rec.counts
    return counts


# -- reading ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Recorded:
    """One recorded message."""

    topic: str
    log_time_ns: int
    """Receive time at the recorder, ns since the Unix epoch."""
    data: bytes
    encoding: str


@dataclass
class Recording:
    """A whole recording in memory, in log-time order."""

    messages: list[Recorded]
    fleet: str | None
    truncated: str = ""
    """Why reading stopped early (a torn tail after a kill), or empty for a complete file."""


COVEY_ENCODINGS = (MESSAGE_ENCODING, PRESENCE_ENCODING)


MCAP_MAGIC = MAGIC
MAX_RECORD_BYTES = 256 * 2**20
"""The largest MCAP record read (covey's chunks are 16 KiB to 1 MiB): a torn or corrupted
length field is refused rather than allocated."""
PARTIAL_EXIT = 1
"""The exit status of `covey replay` and `covey record --foxglove-from` when the recording is
cut off or corrupted: what could be read was used, and a warning says how much."""


def iter_recording(path: str | Path) -> Iterator[Recorded | str]:
    """covey's messages in file order (standard Foxglove channels are skipped). Stops at a torn
    tail or a corrupted record (every chunk's CRC is checked), yielding one final str saying
    why."""
    channels: dict[int, Channel] = {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(
                f, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES
            ).records:
                if isinstance(rec, Channel):
                    if rec.message_encoding in COVEY_ENCODINGS:
                        channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is not None:
                        yield Recorded(ch.topic, rec.log_time, rec.data, ch.message_encoding)
                elif isinstance(rec, Metadata) and rec.name == "covey":
                    yield f"fleet={rec.metadata.get('fleet', '')}"
                elif isinstance(rec, DataEnd | Footer):
                    return
                elif isinstance(rec, Schema):
                    continue
        except EndOfFile:
            yield (
                f"cut off near byte {f.tell()}: the file ends without a summary or footer "
                "(recorder killed?)"
            )
        except Exception as exc:  # noqa: BLE001 - whatever the reader trips on: the rest is lost
            why = " ".join(str(exc).split())[:160] or type(exc).__name__
            yield f"unreadable from near byte {f.tell()} on ({type(exc).__name__}: {why})"


def read_recording(path: str | Path) -> Recording:
    """Load a recording (complete or cut off by a kill), sorted by log time. Raises
    FileNotFoundError or ValueError (not an MCAP file) saying why in one line."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"no recording at {path}")
    with open(path, "rb") as f:
        head = f.read(len(MCAP_MAGIC))
    if not MCAP_MAGIC.startswith(head):  # a shorter prefix: cut off at once, read as empty
        raise ValueError(f"{path} is not an MCAP file (it does not start with the MCAP magic)")
    msgs: list[Recorded] = []
    fleet, truncated = None, ""
    for item in iter_recording(path):
        if isinstance(item, Recorded):
            msgs.append(item)
        elif item.startswith("fleet="):
            fleet = item[len("fleet=") :] or None
        else:
            truncated = item
    if fleet is None:
        for m in msgs:
            parsed = keys.parse_vehicle_key(m.topic)
            if parsed is not None:
                fleet = parsed[0]
                break
    msgs.sort(key=lambda m: m.log_time_ns)
    return Recording(msgs, fleet, truncated)


def partial_warning(rec: Recording, path: str | Path) -> str:
    """One line for a cut-off or corrupted recording: why, and what was kept."""
    info = summarise(rec)
    kinds = ", ".join(f"{n} {kind}" for kind, n in info["counts"].items()) or "nothing"
    return (
        f"warning: {path} is incomplete, {rec.truncated}; kept {info['messages']} messages "
        f"({kinds}) over {info['duration_s']:.1f} s"
    )


def add_foxglove_channels(
    src: str | Path,
    dst: str | Path,
    cfg: FoxgloveConfig = FoxgloveConfig(),
    recording: Recording | None = None,
) -> dict[str, int]:
    """Write `dst`: the covey channels of recording `src` (or of `recording`, read from it
    already), unchanged (same bytes and log times), plus the standard Foxglove channels made
    from them. Returns message counts by kind.

    Raises FileNotFoundError or ValueError (not an MCAP file, or dst is src) saying why."""
    src, dst = Path(src), Path(dst)
    rec = recording if recording is not None else read_recording(src)
    if dst.exists() and dst.resolve() == src.resolve():
        raise ValueError(f"the output {dst} would overwrite the recording it reads")
    with open(dst, "wb") as out:
        sink = McapSink(
            out, rec.fleet or "covey", 1024 * 1024, 60.0, foxglove=cfg, foxglove_worker=False
        )
        for m in rec.messages:
            sink.put(m.topic, m.data, m.log_time_ns)
        sink.close()
    return dict(sink.counts)


def summarise(rec: Recording) -> dict:
    """What `covey record --info` prints: vehicles, duration, counts and rates per kind."""
    counts: dict[str, int] = {}
    per_vehicle: dict[int, int] = {}
    bad = 0
    for m in rec.messages:
        leaf = _leaf(m.topic)
        counts[leaf] = counts.get(leaf, 0) + 1
        if leaf == "state":
            try:
                state = schema.VehicleState.decode(m.data)
            except schema.DecodeError:
                bad += 1
                continue
            per_vehicle[state.vehicle_id] = per_vehicle.get(state.vehicle_id, 0) + 1
    t0 = rec.messages[0].log_time_ns if rec.messages else 0
    t1 = rec.messages[-1].log_time_ns if rec.messages else 0
    duration_s = (t1 - t0) / 1e9
    names = {
        "state": "states",
        "event": "events",
        "trace": "traces",
        "cmd": "commands",
        "ack": "acks",
        "alive": "presence",
        "other": "other",
    }

    def rate(n: int) -> float:
        return n / duration_s if duration_s > 0 else 0.0

    return {
        "fleet": rec.fleet,
        "vehicles": sorted(per_vehicle),
        "start_ns": t0,
        "duration_s": duration_s,
        "messages": len(rec.messages),
        "counts": {names[k]: v for k, v in sorted(counts.items())},
        "rates_hz": {names[k]: rate(v) for k, v in sorted(counts.items())},
        "state_rate_hz_by_vehicle": {vid: rate(n) for vid, n in sorted(per_vehicle.items())},
        "malformed_states": bad,
        "complete": not rec.truncated,
        "truncated": rec.truncated,
    }


def format_info(info: dict, path: str = "") -> str:
    lines = [
        f"recording   {path}",
        f"fleet       {info['fleet']}",
        f"vehicles    {', '.join(map(str, info['vehicles'])) or 'none'}",
        f"duration    {info['duration_s']:.2f} s",
        f"messages    {info['messages']}"
        + ("" if info["complete"] else f"   (cut off: {info['truncated']})"),
        "",
        f"{'kind':<10} {'count':>8} {'rate Hz':>9}",
    ]
    for kind, n in info["counts"].items():
        lines.append(f"{kind:<10} {n:>8} {info['rates_hz'][kind]:>9.2f}")
    if info["state_rate_hz_by_vehicle"]:
        lines += ["", f"{'vehicle':<10} {'state Hz':>9}"]
        lines += [f"{vid:<10} {hz:>9.2f}" for vid, hz in info["state_rate_hz_by_vehicle"].items()]
    return "\n".join(lines)
