"""A recording's Foxglove channels, made off the recorder's hot path: in a child process.

The recorder's writer thread writes covey's raw bytes in chunks, and at each flush hands the
uncompressed records of the chunks it wrote since the last one (it has built them anyway) to
`FoxgloveWorker`. The child (`main()` below, at the lowest priority) reads covey's messages
back out of them, converts them (recording/foxglove_channels.py, the states as arrays), packs the standard messages into finished, compressed MCAP chunks
(recording/mcap_chunks.py), and sends those back; the writer thread writes each into the same file
as one blob. The recorder's process so pays nothing per message for the standard channels, only
a few pipe frames and blob writes per flush, and its GIL stays with Zenoh's callbacks: with the
conversion in the writer thread, a saturating burst lost 18 % of its states (issue 17).

`FoxgloveChunks` is the conversion -> chunks step itself. The child runs it;
`add_foxglove_channels` and `McapSink(foxglove_worker=False)` run it in-process, which is the
reference the child is tested against.

Pipe protocol, both ways: frames of u32 length + pickle (the child is ours, started by us, and
talks only to us). Parent -> child: a setup dict, then per flush a list of raw chunks' records
(bytes), then None = end of input. Child -> parent: per flush the list of BuiltChunks made from
it, then ("done", refused).
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import queue
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.records import Channel, Schema

from recording.foxglove_channels import Converter, FoxgloveConfig
from recording.mcap_chunks import MAX_ID, BuiltChunk, ChunkBuilder, PlainReader

log = logging.getLogger(__name__)

FIRST_ID = 0xE000
"""Schema and channel ids of the standard channels start here (three or so per vehicle: room
for ~2,700 vehicles); covey's own stay below (a topic per vehicle, kind and grid cell)."""
WORKER_NICE = 19
"""The child runs at the lowest priority: where the cores are short, receiving the mesh (what
cannot be had again) goes first, and the conversion catches up when they are free (close()
waits for it). Measured in a saturating burst on 2 busy cores (bench/record_throughput.py):
nice 0 and 5 cost the recording states, 19 did not, beyond the noise."""
DEFER_ABOVE_HZ = 4000.0
"""While the recorder takes in more covey messages per second than this, the worker is handed
nothing: on this project's 2-core VM, converting beside a recorder at 6,500 states/s sustained
cost ~2 % of the states, and in a saturating burst ~6 %, even at nice 19 (tiny Zenoh queues
overflow while the worker holds a core), while at 4,000/s no loss beyond the noise showed
(bench/record_throughput.py). It catches up when the rate falls, or at close."""
MAX_DEFERRED_BYTES = 64 * 1024 * 1024
"""...but no more than this of raw records is held back (about 100 s at 6,500 states/s)."""
MAX_CHUNK_BYTES = 1024 * 1024
"""A chunk of standard channels is cut at the end of each flush's conversion, or here: few
chunks keep the per-chunk costs (pipe frames, indexes) off the recorder."""
_LEN = struct.Struct("<I")


class FoxgloveChunks:
    """covey messages in, finished MCAP chunks of the standard Foxglove channels out.

    Channel and schema ids run from FIRST_ID to MAX_ID; a topic beyond them (more than ~2,700
    vehicles) is not drawn and is counted in `refused`."""

    def __init__(self, cfg: FoxgloveConfig, max_chunk_bytes: int = MAX_CHUNK_BYTES) -> None:
        self._conv = Converter(cfg)
        self._reader = PlainReader()
        self._builder = ChunkBuilder()
        self._max_chunk_bytes = max_chunk_bytes
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._next_id = FIRST_ID
        self.messages = 0
        """Standard messages made so far."""
        self.refused = 0
        """Standard messages not written: their topic had no channel id left."""

    def _channel(self, out) -> int | None:
        cid = self._channel_ids.get(out.topic)
        if cid is not None:
            return cid
        spec = out.schema
        sid = self._schema_ids.get(spec.name)
        if self._next_id + (sid is None) > MAX_ID:
            return None
        if sid is None:
            sid = self._schema_ids[spec.name] = self._next_id
            self._next_id += 1
            self._builder.add_schema(Schema(sid, spec.data, spec.encoding, spec.name))
        cid = self._channel_ids[out.topic] = self._next_id
        self._next_id += 1
        self._builder.add_channel(Channel(cid, out.topic, spec.message_encoding, {}, sid))
        return cid

    def add(self, plains: list[bytes]) -> list[BuiltChunk]:
        """Convert the covey messages of raw chunks (BuiltChunk.plain, in file order); returns
        the chunks they filled, the last one cut at the end (so that the file holds a flush's
        standard channels as soon as they are made)."""
        chunks: list[BuiltChunk] = []
        builder = self._builder
        items = [(t, d, r) for plain in plains for t, r, d in self._reader.messages(plain)]
        for (_, _, recv_ns), outs in zip(items, self._conv.convert_all(items), strict=True):
            for out in outs:
                cid = self._channel(out)
                if cid is None:
                    self.refused += 1
                    continue
                builder.add(cid, out.log_time_ns, out.data, recv_ns)
                self.messages += 1
            if builder.size >= self._max_chunk_bytes and (full := builder.build()) is not None:
                chunks.append(full)
        last = builder.build()
        if last is not None:
            chunks.append(last)
        return chunks


# -- the pipe ----------------------------------------------------------------------------------
def _send(out: IO[bytes], obj: object) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    out.write(_LEN.pack(len(data)))
    out.write(data)
    out.flush()


def _recv(inp: IO[bytes]) -> Any:
    """The next frame; EOFError when the other side has gone."""
    head = inp.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("the pipe closed")
    (n,) = _LEN.unpack(head)
    data = inp.read(n)
    if len(data) < n:
        raise EOFError("the pipe closed inside a frame")
    return pickle.loads(data)


@dataclass(frozen=True)
class WorkerDone:
    """The worker has sent its last chunk (error empty), or died (error says how)."""

    error: str = ""
    refused: int = 0
    """Standard messages the worker did not write (FoxgloveChunks.refused)."""


class FoxgloveWorker:
    """Parent side of the child process. `send()` never blocks (a thread feeds the pipe); every
    chunk the child returns, and finally a WorkerDone, is passed to `deliver` from a reader
    thread. Call `end()` after the last batch, then `close()`."""

    def __init__(
        self, cfg: FoxgloveConfig, deliver: Callable[[BuiltChunk | WorkerDone], None]
    ) -> None:
        # The child imports this very comms (first on its path, before the working folder),
        # and lowers its priority before those imports (numpy, foxglove, mcap: ~0.3 s of CPU).
        # It ignores SIGINT: a terminal's Ctrl-C reaches the whole process group, and is for
        # the recorder, which then ends the child itself once the last chunks are back.
        root = str(Path(__file__).resolve().parent.parent)
        start = (
            "import contextlib, os, signal, sys\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
            f"sys.path.insert(0, {root!r})\n"
            f"with contextlib.suppress(OSError): os.nice({WORKER_NICE})\n"
            "from recording.foxglove_worker import main\n"
            "raise SystemExit(main())\n"
        )
        self._proc = subprocess.Popen(
            [sys.executable, "-c", start], stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )
        self._deliver = deliver
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._outbox.put({"cfg": cfg})
        self._ended = False
        self.sent = 0
        """Flushes sent to the child."""
        self.converted = 0
        """Flushes whose chunks have come back: sent - converted is how far behind it is."""
        self._sender = threading.Thread(target=self._feed, name="covey-foxglove-feed", daemon=True)
        self._reader = threading.Thread(target=self._read, name="covey-foxglove-read", daemon=True)
        self._sender.start()
        self._reader.start()

    def send(self, plains: list[bytes]) -> None:
        """Raw chunks' records (BuiltChunk.plain) to convert, in file order."""
        if not self._ended:
            self.sent += 1
            self._outbox.put(plains)

    def end(self) -> None:
        """No more batches: the child finishes its chunks and says done."""
        if not self._ended:
            self._ended = True
            self._outbox.put(None)

    def _feed(self) -> None:
        pipe = self._proc.stdin
        assert pipe is not None  # Popen(stdin=PIPE)
        try:
            while True:
                item = self._outbox.get()
                _send(pipe, item)
                if item is None:
                    break
        except OSError:
            pass  # the child died; _read reports it
        finally:
            with contextlib.suppress(OSError):
                pipe.close()

    def _read(self) -> None:
        pipe = self._proc.stdout
        assert pipe is not None  # Popen(stdout=PIPE)
        while True:
            try:
                item = _recv(pipe)
            except (EOFError, OSError, pickle.UnpicklingError) as exc:
                rc = self._proc.wait()
                self._deliver(
                    WorkerDone(f"the Foxglove worker stopped early (exit code {rc}: {exc})")
                )
                return
            if isinstance(item, list):
                for chunk in item:
                    self._deliver(chunk)
                self.converted += 1
            else:
                self._deliver(WorkerDone(refused=item[1]))
                return

    def close(self, timeout_s: float = 10.0) -> None:
        """Wait for the child after its done (or kill it if it lingers)."""
        self.end()
        self._sender.join(timeout_s)
        self._reader.join(timeout_s)
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        if self._proc.stdout is not None:
            self._proc.stdout.close()


# -- the child ---------------------------------------------------------------------------------
def main() -> int:
    """Child: setup frame, then batches until None; chunks back on stdout."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # a stray print must not corrupt the frames
    try:
        setup = _recv(inp)
        chunks = FoxgloveChunks(setup["cfg"])
        while (plains := _recv(inp)) is not None:
            _send(out, chunks.add(plains))
        _send(out, ("done", chunks.refused))
    except (EOFError, BrokenPipeError):
        return 0  # the recorder went away (killed?): nothing left to write to
    return 0
