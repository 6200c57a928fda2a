"""Bounded reading of the files a user hands covey, before any parser sees them.

Key files and the config inside a weights file are JSON, Zenoh configs JSON5, weights npz:
every parser of them recurses on nesting (Python's json raises RecursionError, Zenoh's Rust
parser overflows its stack and kills the process) or trusts the sizes a file declares (numpy
allocates what an npz header says). So each file is read here with a size limit, its nesting
counted by a small scanner that skips strings and comments, and an npz's members checked from
their headers alone. A refusal is a BadFileError: one line that names the file and why.
"""

from __future__ import annotations

import json
import os
import re
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

MAX_DEPTH = 32
"""The deepest nesting of objects and arrays accepted in a JSON or JSON5 file (covey's own
files nest 4 deep, the shipped Zenoh configs 5)."""


class BadFileError(ValueError):
    """A file covey was given cannot be used; the message is one line that says why."""


def read_bounded(path: str | os.PathLike[str], max_bytes: int, what: str) -> bytes:
    """The bytes of the regular file `path`, refused (BadFileError) if it is missing, not a
    regular file (a FIFO would block the read), unreadable, or over `max_bytes`."""
    p = Path(path).expanduser()
    try:
        st = p.stat()
        if not stat.S_ISREG(st.st_mode):
            raise BadFileError(f"{what} {p} is not a regular file")
        if st.st_size > max_bytes:
            raise BadFileError(f"{what} {p} is {st.st_size} bytes, over the {max_bytes} limit")
        with open(p, "rb") as f:
            raw = f.read(max_bytes + 1)
    except FileNotFoundError:
        raise BadFileError(f"{what} {p} does not exist") from None
    except OSError as exc:
        raise BadFileError(f"{what} {p}: cannot read it ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:  # it grew while we looked
        raise BadFileError(f"{what} {p} is over the {max_bytes} byte limit")
    return raw


# A string in either quote (escapes and JSON5 line continuations inside), a // or /* */
# comment, or one bracket; whichever starts first wins, as in a JSON5 parser.
_TOKENS = re.compile(r""""(?:[^"\\]|\\.)*"|'(?:[^'\\]|\\.)*'|//[^\n]*|/\*.*?\*/|[\[\]{}]""", re.S)


def nesting_depth(text: str, limit: int = MAX_DEPTH) -> int:
    """The deepest nesting of {} and [] in JSON or JSON5 `text`, brackets inside strings and
    comments not counted; it stops counting once past `limit`. An unterminated string or
    comment is scanned as if it were not one, which can only count more."""
    depth = peak = 0
    for m in _TOKENS.finditer(text):
        c = m.group()
        if c in "{[":
            depth += 1
            if depth > peak:
                peak = depth
                if peak > limit:
                    break
        elif c in "}]":
            depth = max(depth - 1, 0)
    return peak


def check_depth(text: str, what: str, limit: int = MAX_DEPTH) -> None:
    """Refuse `text` (BadFileError) if it nests deeper than `limit`."""
    if nesting_depth(text, limit) > limit:
        raise BadFileError(f"{what} nests deeper than {limit} levels")


def decode_utf8(raw: bytes, what: str) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BadFileError(f"{what} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def parse_json(text: str, what: str, limit: int = MAX_DEPTH) -> object:
    """`text` parsed as JSON after its nesting is checked; BadFileError (one line) if it is
    too deep or not JSON."""
    check_depth(text, what, limit)
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:  # ValueError: JSONDecodeError, huge ints
        raise BadFileError(f"{what} is not JSON ({' '.join(str(exc).split())[:120]})") from None


# -- npz -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArrayHeader:
    """What an npz member's .npy header declares, read without loading its data."""

    shape: tuple[int, ...]
    dtype: np.dtype
    """A numpy dtype."""

    @property
    def nbytes(self) -> int:
        n = 1
        for d in self.shape:
            n *= d
        return n * self.dtype.itemsize


MAX_NPZ_MEMBERS = 256


def npz_headers(path: str | os.PathLike[str], what: str = "weights file") -> dict[str, ArrayHeader]:
    """Each array of the npz archive `path` by name (".npy" dropped), from the headers alone.
    BadFileError if it is not an npz archive or a member is not a plain .npy array (an object
    array would need pickle)."""
    import numpy as np
    from numpy.lib import format as npy

    p = Path(path)
    out: dict[str, ArrayHeader] = {}
    try:
        if not zipfile.is_zipfile(p):
            raise BadFileError(f"{what} {p} is not an npz archive (not a zip file)")
        with zipfile.ZipFile(p) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_NPZ_MEMBERS:
                raise BadFileError(f"{what} {p} has {len(infos)} members, over {MAX_NPZ_MEMBERS}")
            for info in infos:
                name = info.filename
                if not name.endswith(".npy"):
                    raise BadFileError(f"{what} {p}: member {name!r} is not a .npy array")
                try:
                    with zf.open(info) as f:
                        version = npy.read_magic(f)
                        if version == (1, 0):
                            shape, _, dtype = npy.read_array_header_1_0(f)
                        elif version == (2, 0):
                            shape, _, dtype = npy.read_array_header_2_0(f)
                        else:
                            raise BadFileError(f"{what} {p}: {name} has .npy version {version}")
                except (ValueError, zipfile.BadZipFile, EOFError) as exc:  # not BadFileError
                    if isinstance(exc, BadFileError):
                        raise
                    why = " ".join(str(exc).split())[:120]
                    raise BadFileError(f"{what} {p}: member {name} is unreadable ({why})") from None
                if dtype.hasobject:
                    raise BadFileError(f"{what} {p}: {name} holds Python objects (pickle); refused")
                out[name[: -len(".npy")]] = ArrayHeader(tuple(shape), np.dtype(dtype))
    except BadFileError:
        raise
    except FileNotFoundError:
        raise BadFileError(f"{what} {p} does not exist") from None
    except OSError as exc:
        raise BadFileError(f"{what} {p}: cannot read it ({exc.strerror or exc})") from None
    except (ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:  # a torn header
        raise BadFileError(
            f"{what} {p} is not a readable npz archive ({' '.join(str(exc).split())[:120]})"
        ) from None
    return out
