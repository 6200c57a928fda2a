"""argparse value types shared by the station's and the tools' CLIs: each refuses a bad value
with a message that names the unit (argparse turns it into a one-line error and exit 2). Also
`stop_on_signals`, the way those CLIs stop."""

from __future__ import annotations

import argparse
import math
import signal
import threading
from collections.abc import Callable


def port(text: str) -> int:
    """A TCP port, 0..65535 (0 = any free port)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{v} is outside 0..65535")
    return v


def finite(
    unit: str, *, minimum: float = 0.0, inclusive: bool = False, allow_inf: bool = False
) -> Callable[[str], float]:
    """A finite number of `unit` above `minimum` (or at least it, with `inclusive`); with
    `allow_inf`, also "inf" (for "as fast as possible")."""
    bound = f">= {minimum:g}" if inclusive else f"> {minimum:g}"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number of {unit}") from None
        ok = (math.isfinite(v) or (allow_inf and v == math.inf)) and (
            v >= minimum if inclusive else v > minimum
        )
        if not ok:
            raise argparse.ArgumentTypeError(f"{text!r} must be a finite number of {unit} {bound}")
        return v

    return parse


def stop_on_signals() -> threading.Event:
    """An Event that SIGINT and SIGTERM set (from the main thread only: Python's rule)."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    return stop
