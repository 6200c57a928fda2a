"""Shared test vectors of the C separation filter (covey_safety.c) and policy/safety.py.

A `FilterCase` holds float32 values, so the C filter and the numpy reference see the same
bits; `line` writes it for firmware/host/covey_driver.c ("S" lines), `expected_status` is
the reference of the filter's input checks (covey_safety.h lists their order) and `mutate`
makes hostile copies for the sanitizer fuzz.
"""

from __future__ import annotations

from dataclasses import astuple, dataclass, field, replace

import numpy as np

from firmware.cases import (
    MAX_ABS_POS_M,
    MAX_CRUISE_SPEED_M_S,
    MAX_INPUTS,
    MIN_CRUISE_SPEED_M_S,
    STATUS,
    _f,
)
from policy.safety import SafetyConfig

F32 = np.float32
MAX_ABS_VEL_M_S = F32(1.0e3)
RADIUS_RANGE_M = (F32(0.01), F32(1000.0))
MAX_MARGIN = F32(10.0)
TIME_RANGE_S = (F32(1.0e-3), F32(1000.0))
BAD = (float("nan"), float("inf"), float("-inf"), 3.0e38, -2.0e5, 1.5e3, -0.0, 0.0)


@dataclass(frozen=True)
class FilterCase:
    """One filter call in world units (float32 values)."""

    cfg: tuple = astuple(SafetyConfig())
    """radius_m, margin, time_horizon_s, dt_s, max_speed_m_s, responsibility (default: flight's,
    policy.safety.SafetyConfig)."""
    own: tuple = (0.0, 0.0, 0.0, 0.0)
    """pos_n, pos_e, vel_n, vel_e."""
    pref: tuple = (0.0, 0.0)
    nbrs: list = field(default_factory=list)
    """[(pos_n, pos_e, vel_n, vel_e)]."""
    n_nbrs: int | None = None
    """Count passed to the core (None = len(nbrs))."""

    @property
    def count(self) -> int:
        return len(self.nbrs) if self.n_nbrs is None else self.n_nbrs


def _f32s(values) -> tuple:
    return tuple(float(F32(v)) for v in values)


def random_case(
    rng: np.random.Generator, n_nbrs: int | None = None, scale: float = 1.0
) -> FilterCase:
    """A random conflict: neighbours around the vehicle (some overlapping), velocities up to
    the speed limit, the preference sometimes beyond it. `scale` multiplies distances and speeds."""
    n = int(rng.integers(0, 13)) if n_nbrs is None else n_nbrs
    s = float(scale)
    own_pos = rng.uniform(-50, 50, 2) * s
    own = _f32s([*own_pos, *(rng.uniform(-1, 1, 2) * s * 0.8)])
    pref = _f32s(rng.uniform(-1.3, 1.3, 2) * s)
    nbrs = []
    for _ in range(n):
        r = rng.uniform(0.5, 14.0) * s
        a = rng.uniform(-np.pi, np.pi)
        pos = own_pos + r * np.array([np.cos(a), np.sin(a)])
        nbrs.append(_f32s([*pos, *(rng.uniform(-1, 1, 2) * s * 0.8)]))
    cfg = _f32s((3.0 * s, 0.1, 4.0, 0.1, 1.0 * s, 0.5))
    return FilterCase(cfg, own, pref, nbrs)


def line(c: FilterCase) -> str:
    """The driver line ("S ...")."""
    toks = ["S", *map(_f, c.cfg), *map(_f, c.own), *map(_f, c.pref), str(c.count), str(len(c.nbrs))]
    for nb in c.nbrs:
        toks += [_f(v) for v in nb]
    return " ".join(toks)


def sparse_line(c: FilterCase, goal: tuple) -> str:
    """The driver line of covey_sparse_choose ("P ..."): c's inputs, its preference being the
    policy's velocity, and a goal."""
    toks = ["P", *map(_f, c.cfg), *map(_f, c.own), *map(_f, c.pref), *map(_f, goal)]
    toks += [str(c.count), str(len(c.nbrs))]
    for nb in c.nbrs:
        toks += [_f(v) for v in nb]
    return " ".join(toks)


def parse_sparse_output(text: str) -> dict:
    """status vel_n vel_e straight n_encounters."""
    t = text.split()
    return {
        "status": int(t[0]),
        "vel": np.array([float(t[1]), float(t[2])]),
        "straight": int(t[3]),
        "n_encounters": int(t[4]),
    }


def parse_output(text: str) -> dict:
    """status vel_n vel_e n_lines changed infeasible."""
    t = text.split()
    return {
        "status": int(t[0]),
        "vel": np.array([float(t[1]), float(t[2])]),
        "n_lines": int(t[3]),
        "changed": int(t[4]),
        "infeasible": int(t[5]),
    }


def _status(values, bounds) -> int:
    """Non-finite anywhere first, then any |value| beyond its bound."""
    v = np.asarray(values, dtype=np.float32)
    if not np.all(np.isfinite(v)):
        return STATUS["nonfinite"]
    if np.any(np.abs(v) > np.asarray(bounds, dtype=np.float32)):
        return STATUS["range"]
    return STATUS["ok"]


def _config_status(c: FilterCase) -> int:
    """The config, then the neighbour count (covey_safety.h's first checks)."""
    cfg = np.asarray(c.cfg, dtype=np.float32)
    if not np.all(np.isfinite(cfg)):
        return STATUS["nonfinite"]
    radius, margin, horizon, dt, vmax, resp = cfg
    ok = (
        RADIUS_RANGE_M[0] <= radius <= RADIUS_RANGE_M[1]
        and 0 <= margin <= MAX_MARGIN
        and TIME_RANGE_S[0] <= horizon <= TIME_RANGE_S[1]
        and TIME_RANGE_S[0] <= dt <= TIME_RANGE_S[1]
        and MIN_CRUISE_SPEED_M_S <= vmax <= MAX_CRUISE_SPEED_M_S
        and 0 < resp <= 1
    )
    if not ok or not 0 <= c.count <= MAX_INPUTS:
        return STATUS["range"]
    return STATUS["ok"]


def _first_fault(checks) -> int:
    """The first fault of (values, bounds) pairs in order (each non-finite before range)."""
    for values, bounds in checks:
        st = _status(values, bounds)
        if st != STATUS["ok"]:
            return st
    return STATUS["ok"]


TRACK_BOUNDS = (MAX_ABS_POS_M, MAX_ABS_POS_M, MAX_ABS_VEL_M_S, MAX_ABS_VEL_M_S)


def expected_status(c: FilterCase) -> int:
    """The fault covey_safety_filter must return (the order of covey_safety.h)."""
    st = _config_status(c)
    if st != STATUS["ok"]:
        return st
    return _first_fault(
        [
            (c.own, TRACK_BOUNDS),
            (c.pref, (MAX_ABS_VEL_M_S, MAX_ABS_VEL_M_S)),
            *((nb, TRACK_BOUNDS) for nb in c.nbrs[: c.count]),
        ]
    )


def expected_sparse_status(c: FilterCase, goal: tuple) -> int:
    """The fault covey_sparse_choose must return (covey_guidance.h): the filter's order with
    the goal checked between the own state and the policy's velocity (c.pref)."""
    st = _config_status(c)
    if st != STATUS["ok"]:
        return st
    return _first_fault(
        [
            (c.own, TRACK_BOUNDS),
            (goal, (MAX_ABS_POS_M, MAX_ABS_POS_M)),
            (c.pref, (MAX_ABS_VEL_M_S, MAX_ABS_VEL_M_S)),
            *((nb, TRACK_BOUNDS) for nb in c.nbrs[: c.count]),
        ]
    )


def mutate(c: FilterCase, rng: np.random.Generator) -> FilterCase:
    """A hostile copy: a bad value in the config, own state, preference or a neighbour, or a bad
    count; sometimes a valid but extreme config (tiny dt, huge horizon)."""
    kind = int(rng.integers(0, 6))
    bad = float(rng.choice(BAD))
    if kind == 0:
        cfg = list(c.cfg)
        cfg[int(rng.integers(0, 6))] = float(rng.choice([*BAD, 1e-3, 1000.0, 1.0, 0.011]))
        return replace(c, cfg=tuple(cfg))
    if kind == 1:
        own = list(c.own)
        own[int(rng.integers(0, 4))] = bad
        return replace(c, own=tuple(own))
    if kind == 2:
        pref = list(c.pref)
        pref[int(rng.integers(0, 2))] = bad
        return replace(c, pref=tuple(pref))
    if kind == 3 and c.nbrs:
        nbrs = [list(nb) for nb in c.nbrs]
        nbrs[int(rng.integers(0, len(nbrs)))][int(rng.integers(0, 4))] = bad
        return replace(c, nbrs=[tuple(nb) for nb in nbrs])
    if kind == 4:
        return replace(c, n_nbrs=int(rng.choice([-1, -7, len(c.nbrs), MAX_INPUTS + 1, 2**31 - 1])))
    # coincident vehicles and identical velocities: the degenerate geometry
    nbrs = [tuple(c.own) for _ in range(int(rng.integers(1, 4)))] + list(c.nbrs)
    return replace(c, nbrs=nbrs[:MAX_INPUTS])
