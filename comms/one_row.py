"""Read-only arrays shared by one-row fast paths (an agent's one vehicle, every tick).

An agent's tick pays several microseconds of a cold cache for every small numpy call
(docs/companion.md, "Round fifteen"); its one-row paths work on Python floats and hand back
these constants instead of building a (1,) array each tick. They are read-only: a caller that
tried to write one would raise, not corrupt the next tick.
"""

from __future__ import annotations

import numpy as np


def frozen(a: np.ndarray) -> np.ndarray:
    """`a`, made read-only (returned for chaining)."""
    a.flags.writeable = False
    return a


ROW0 = frozen(np.zeros(1, np.intp))
"""Row 0 alone, as row indices."""
NO_ROWS = frozen(np.zeros(0, np.intp))
"""No row, as row indices."""
FLAG = (frozen(np.zeros(1, bool)), frozen(np.ones(1, bool)))
"""A one-row flag: FLAG[False] or FLAG[True]."""
