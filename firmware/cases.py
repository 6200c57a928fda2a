"""Shared firmware test cases: random weights, random scenarios, fuzz mutations.

One scenario is a `Case` in world units with float32 values, so that the C core,
the numpy runtime and the Cortex-M build all see exactly the same bits. `expected_status`
is the reference of the core's input checks (covey_policy.h lists their order).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

F32 = np.float32
MAX_NEIGHBOURS = 40  # COVEY_MAX_NEIGHBOURS
MAX_INPUTS = 64  # COVEY_MAX_INPUTS
MAX_ABS_POS_M = F32(1.0e5)
MAX_ABS_HEADING_RAD = F32(12.5663706)
MIN_SEPARATION_M = F32(0.01)
MAX_SEPARATION_M = F32(1000.0)
MIN_CRUISE_SPEED_M_S = F32(0.01)
MAX_CRUISE_SPEED_M_S = F32(100.0)
MAX_ABS_FEATURE = F32(1.0e9)
U64_MAX = 2**64 - 1

STATUS = {"ok": 0, "null": 1, "nonfinite": 2, "range": 3, "stale": 4}


def write_random_npz(
    path,
    encoding="paper",
    order="index",
    hidden=63,
    head=(64, 64, 2),
    dist_scale=1.0,
    sense_range=0.0,
    seed=0,
    scale=0.4,
) -> Path:
    """A weights file in the spec's format with random float32 weights (for tests)."""
    rng = np.random.default_rng(seed)
    x = 3 if encoding == "paper" else 5
    g = 1 if encoding == "paper" else 2

    def rand(*shape):
        return (
            rng.standard_normal(shape) * scale / np.sqrt(shape[-1] if len(shape) > 1 else 4)
        ).astype(np.float32)

    arrays = {
        "lstm.weight_ih": rand(4 * hidden, x) * F32(3.0),
        "lstm.weight_hh": rand(4 * hidden, hidden) * F32(3.0),
        "lstm.bias": rand(4 * hidden),
    }
    n_in = hidden + g
    for k, n_out in enumerate(head):
        arrays[f"head.{k}.weight"] = rand(n_out, n_in) * F32(3.0)
        arrays[f"head.{k}.bias"] = rand(n_out)
        n_in = n_out
    cfg = {
        "encoding": encoding,
        "order": order,
        "dist_scale": dist_scale,
        "sense_range": sense_range,
        "hidden": hidden,
        "input": x,
        "head": list(head),
        "encoder": "lstm",
    }
    path = Path(path)
    np.savez(path, config=np.array(json.dumps(cfg)), **arrays)
    return path


@dataclass
class Case:
    """One guidance call in world units (metres, rad, microseconds), float32 values."""

    sep_m: float = 3.0
    cruise_m_s: float = 1.0
    max_nbr_age_us: int = 1_000_000
    max_own_age_us: int = 500_000
    max_nbrs: int = MAX_NEIGHBOURS
    own: tuple = (0.0, 0.0, 0.0, 0)  # n, e, heading, stamp_us
    goal: tuple = (10.0, 0.0)
    now_us: int = 0
    nbrs: list = field(default_factory=list)  # [(n, e, heading, stamp_us)]
    n_nbrs: int | None = None  # count passed to the core; None = len(nbrs)

    @property
    def count(self) -> int:
        return len(self.nbrs) if self.n_nbrs is None else self.n_nbrs

    def fresh_nbrs(self) -> list:
        return [nb for nb in self.nbrs if self.now_us - nb[3] <= self.max_nbr_age_us]


def _f(x) -> str:
    x = float(F32(x))
    if np.isnan(x):
        return "nan"
    return f"{x:.9g}"


def case_line(c: Case) -> str:
    """The driver's input line (firmware/host/covey_driver.c)."""
    parts = [
        "C",
        _f(c.sep_m),
        _f(c.cruise_m_s),
        str(c.max_nbr_age_us),
        str(c.max_own_age_us),
        str(c.max_nbrs),
        _f(c.own[0]),
        _f(c.own[1]),
        _f(c.own[2]),
        str(c.own[3]),
        _f(c.goal[0]),
        _f(c.goal[1]),
        str(c.now_us),
        str(c.count),
        str(min(len(c.nbrs), MAX_INPUTS)),
    ]
    for nb in c.nbrs[:MAX_INPUTS]:
        parts += [_f(nb[0]), _f(nb[1]), _f(nb[2]), str(nb[3])]
    return " ".join(parts)


def action_line(seq, goal_feat, n_steps=None) -> str:
    values = [*np.asarray(seq, np.float32).ravel(), *np.asarray(goal_feat, np.float32).ravel()]
    n = len(seq) if n_steps is None else n_steps
    return " ".join(["A", str(n), str(len(values)), *map(_f, values)])


def parse_command_output(line: str) -> dict:
    t = line.split()
    return {
        "status": int(t[0]),
        "vel": np.array([float(t[1]), float(t[2])]),
        "action": np.array([float(t[3]), float(t[4])]),
        "n_used": int(t[5]),
        "n_stale": int(t[6]),
        "n_far": int(t[7]),
        "n_excess": int(t[8]),
    }


def f32(x) -> float:
    return float(F32(x))


def random_case(
    rng: np.random.Generator,
    n_nbrs: int | None = None,
    spread_m: float | None = None,
    stale_fraction: float = 0.1,
) -> Case:
    """A valid scenario: random airframe scaling, positions, headings, some stale neighbours.

    Neighbours lie within +-spread_m (scaled by separation / 3) of the vehicle; by
    default the spread is drawn from 10, 30 or 80 so that sense ranges matter.
    """
    n = int(rng.integers(0, MAX_NEIGHBOURS + 1)) if n_nbrs is None else n_nbrs
    if spread_m is None:
        spread_m = float(rng.choice([10.0, 30.0, 80.0]))
    sep = f32(rng.choice([3.0, rng.uniform(1.0, 10.0)]))
    cruise = f32(rng.choice([1.0, rng.uniform(0.5, 8.0)]))
    centre = rng.uniform(-500, 500, 2)
    now = int(rng.integers(2_000_000, 10**12))
    own = (
        f32(centre[0]),
        f32(centre[1]),
        f32(rng.uniform(-np.pi, np.pi)),
        now - int(rng.integers(0, 400_000)),
    )
    goal = tuple(f32(v) for v in centre + rng.uniform(-200, 200, 2))
    nbrs = []
    for _ in range(n):
        p = centre + rng.uniform(-spread_m, spread_m, 2) * sep / 3.0
        stale = rng.random() < stale_fraction
        age = int(rng.integers(1_000_001, 5_000_000)) if stale else int(rng.integers(0, 1_000_000))
        nbrs.append((f32(p[0]), f32(p[1]), f32(rng.uniform(-np.pi, np.pi)), now - age))
    max_nbrs = int(rng.choice([MAX_NEIGHBOURS, rng.integers(0, MAX_NEIGHBOURS + 1)]))
    return Case(
        sep_m=sep, cruise_m_s=cruise, max_nbrs=max_nbrs, own=own, goal=goal, now_us=now, nbrs=nbrs
    )


# ---- reference of the input checks ------------------------------------------------


def _abs_status(x, bound) -> int:
    x = F32(x)
    if not np.isfinite(x):
        return STATUS["nonfinite"]
    return STATUS["ok"] if abs(x) <= bound else STATUS["range"]


def _fields_status(values, bounds) -> int:
    st = [_abs_status(v, b) for v, b in zip(values, bounds, strict=True)]
    if STATUS["nonfinite"] in st:
        return STATUS["nonfinite"]
    return STATUS["range"] if STATUS["range"] in st else STATUS["ok"]


def expected_status(c: Case) -> int:
    """The fault the core must return for `c` (the order in covey_policy.h)."""
    sep, cruise = F32(c.sep_m), F32(c.cruise_m_s)
    if not (np.isfinite(sep) and np.isfinite(cruise)):
        return STATUS["nonfinite"]
    if not (MIN_SEPARATION_M <= sep <= MAX_SEPARATION_M) or not (
        MIN_CRUISE_SPEED_M_S <= cruise <= MAX_CRUISE_SPEED_M_S
    ):
        return STATUS["range"]
    if not (0 <= c.max_nbrs <= MAX_NEIGHBOURS):
        return STATUS["range"]
    if not (0 <= c.count <= MAX_INPUTS):
        return STATUS["range"]
    vb = (MAX_ABS_POS_M, MAX_ABS_POS_M, MAX_ABS_HEADING_RAD)
    st = _fields_status(c.own[:3], vb)
    if st:
        return st
    if c.own[3] > c.now_us:
        return STATUS["range"]
    if c.now_us - c.own[3] > c.max_own_age_us:
        return STATUS["stale"]
    st = _fields_status(c.goal, (MAX_ABS_POS_M, MAX_ABS_POS_M))
    if st:
        return st
    for nb in c.nbrs[: c.count]:
        if nb[3] > c.now_us:
            return STATUS["range"]
        if c.now_us - nb[3] > c.max_nbr_age_us:
            continue
        st = _fields_status(nb[:3], vb)
        if st:
            return st
    return STATUS["ok"]


BAD_FLOATS = (
    float("nan"),
    float("inf"),
    float("-inf"),
    3.0e38,
    -3.0e38,
    1.0e30,
    1.0e5 * 1.0001,
    -1.0e5 * 1.0001,
    13.0,
    -13.0,
    0.0,
    -0.0,
    1.0e-40,
    -1.0,
    1.0e4,
)
BAD_INTS = (-1, -(2**31), 2**31 - 1, 41, 65, 64, 0, 1)
BAD_STAMPS = (0, U64_MAX, 2**63, 1)


def mutate(c: Case, rng: np.random.Generator) -> Case:
    """`c` with 1 to 3 fields set to hostile values (NaN, inf, huge, negative, future...)."""
    c = replace(c, nbrs=list(c.nbrs))
    for _ in range(int(rng.integers(1, 4))):
        what = int(rng.integers(0, 9))
        bad = float(rng.choice(BAD_FLOATS))
        if what == 0:
            c.sep_m = bad
        elif what == 1:
            c.cruise_m_s = bad
        elif what == 2:
            c.max_nbrs = int(rng.choice(BAD_INTS))
        elif what == 3:
            c.n_nbrs = int(rng.choice(BAD_INTS))
            if c.n_nbrs > len(c.nbrs) and c.n_nbrs <= MAX_INPUTS:
                c.n_nbrs = len(c.nbrs)  # the array must really hold what a valid count claims
        elif what == 4:
            own = list(c.own)
            k = int(rng.integers(0, 4))
            own[k] = int(rng.choice(BAD_STAMPS)) if k == 3 else bad
            c.own = tuple(own)
        elif what == 5:
            goal = list(c.goal)
            goal[int(rng.integers(0, 2))] = bad
            c.goal = tuple(goal)
        elif what in (6, 7) and c.nbrs:
            j = int(rng.integers(0, len(c.nbrs)))
            nb = list(c.nbrs[j])
            k = int(rng.integers(0, 4))
            nb[k] = int(rng.choice(BAD_STAMPS)) if k == 3 else bad
            c.nbrs[j] = tuple(nb)
        else:
            c.now_us = int(rng.choice(BAD_STAMPS))
    return c


def runtime_reference(npz_path, c: Case):
    """(velocity m/s, action, neighbours used) from the numpy runtime, for a valid case.

    The runtime has no clock, so it gets only the neighbours the core keeps as fresh.
    The safety filter is off: the C core implements the network policy alone.
    """
    from policy import features
    from policy.observation import Observation
    from policy.runtime import GuidancePolicy

    pol = GuidancePolicy.load(
        npz_path,
        separation_m=c.sep_m,
        cruise_speed_m_s=c.cruise_m_s,
        safety_filter=False,
        max_neighbours=c.max_nbrs,
    )
    fresh = c.fresh_nbrs()
    nbr_pos = np.array([nb[:2] for nb in fresh], dtype=np.float64).reshape(-1, 2)
    nbr_h = np.array([nb[2] for nb in fresh], dtype=np.float64)
    pos = np.array(c.own[:2], dtype=np.float64)
    goal = np.array(c.goal, dtype=np.float64)
    vel = pol.command(pos, np.zeros(2), c.own[2], goal, nbr_pos, np.zeros_like(nbr_pos), nbr_h)
    s = pol.dist_scale_m
    action = pol.actor.action(Observation.at_rest(pos, c.own[2], goal, nbr_pos, nbr_h))
    _, _, idx = features.observe(
        pos / s, c.own[2], goal / s, nbr_pos / s, nbr_h, pol.obs_cfg, c.max_nbrs
    )
    return vel, action, len(idx)
