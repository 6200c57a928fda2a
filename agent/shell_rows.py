"""The vehicle shell's rows, vectorised: whom a state is tagged for, and the VehicleStates of
the rows that are due (agent/shell.py; what the rows see of their neighbours is in
agent/shell_views.py). Pure functions of the core, this tick's telemetry and the neighbour
snapshot: one copy for one vehicle and for many.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from agent.flight_core import FlightCore, Observed
from agent.neighbours import NeighbourSnapshot
from comms.schema import POS_SIGMA_LIMIT_M, Mode, StateFlag, VehicleState

_MODES = {m.value: m for m in Mode}


@functools.cache
def _state_flag(bits: int) -> StateFlag:
    return StateFlag(bits)


def link_receivers(ext: NeighbourSnapshot, pos_ned_m: np.ndarray, limit: int) -> list[int]:
    """The ids of the (at most `limit`) vehicles of `ext` nearest `pos_ned_m` horizontally,
    traffic left out: whom a state is tagged for (trust/links.py)."""
    if limit <= 0 or not len(ext):
        return []
    if ext.cooperative is None and len(ext) <= limit:  # no traffic, all in: no array maths
        return list(ext.ids)
    idx = np.flatnonzero(ext.column("cooperative", True))
    if idx.size > limit:
        d2 = np.sum((ext.pos_ned_m[idx, :2] - pos_ned_m[:2]) ** 2, axis=1)
        idx = idx[np.argsort(d2, kind="stable")[:limit]]
    ids = ext.ids
    return [ids[i] for i in idx.tolist()]


F8 = np.dtype(float)
"""float64, compared by identity on the one-row paths."""


def stale_mask(ext: NeighbourSnapshot) -> np.ndarray:
    """(len(ext),) which entries are stale (the ids are integers: np.isin's answer)."""
    if not ext.stale_ids:
        return np.zeros(len(ext), bool)
    stale = set(ext.stale_ids)
    return np.array([v in stale for v in ext.ids], bool).reshape(len(ext))


def stale_rows(
    slowed: np.ndarray, pos_m: np.ndarray, ext: NeighbourSnapshot, vertical_band_m: float
) -> np.ndarray:
    """(n,) the rows that guidance slowed for a stale neighbour, or that have one within
    `vertical_band_m` of their altitude (flying or not)."""
    stale = np.array(slowed, bool)
    if ext.stale_ids:
        at = ext.pos_ned_m[stale_mask(ext)]
        dz = np.abs(pos_m[:, None, 2] - at[None, :, 2])
        stale |= (dz <= vertical_band_m).any(axis=1)
    return stale


def vehicle_states(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    seq: np.ndarray,
    rows: np.ndarray,
    bits: np.ndarray | int,
    stamp_ns: int,
) -> list[VehicleState]:
    """The states of `rows`, stamped `stamp_ns`, with each row's `seq` and its flags: `bits`
    (n,) (the shell's: open mode, filter, stale; one int: the same for every row) with the
    core's failsafes, a goal, a lost autopilot link. Battery and position 1-sigma are clamped
    to what a state carries, the heading wrapped to [-pi, pi).

    One row (an agent's every tick) takes `_one_vehicle_state`, the same state in Python
    floats without the small array calls; `vehicle_states_rows` is the general path and its
    reference (tests compare them)."""
    if len(rows) == 1:
        state = _one_vehicle_state(core, obs, pos_sigma_m, ids, seq, rows, bits, stamp_ns)
        if state is not None:
            return [state]
    return vehicle_states_rows(core, obs, pos_sigma_m, ids, seq, rows, bits, stamp_ns)


def vehicle_states_rows(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    seq: np.ndarray,
    rows: np.ndarray,
    bits: np.ndarray | int,
    stamp_ns: int,
) -> list[VehicleState]:
    """`vehicle_states` of any number of rows, as arrays."""
    # whole arrays to Python floats once: per-row numpy access costs more than the rest
    pos, vel = obs.pos_m[rows].tolist(), obs.vel_m_s[rows].tolist()
    targets = core.targets()[rows]
    has = ~np.isnan(targets[:, 0])
    goal = np.where(has[:, None], targets, 0.0).tolist()
    hdg = (np.remainder(core.heading_rad[rows] + math.pi, 2 * math.pi) - math.pi).tolist()
    # flags as ints, one enum per distinct value (enum arithmetic per row cost more than the
    # rest of the state)
    shell_bits = np.asarray(bits, np.int64)
    bits = (
        (shell_bits[rows] if shell_bits.ndim else np.full(len(rows), shell_bits))
        | np.array([int(core.failsafes[r].flags) for r in rows.tolist()], np.int64)
        | np.where(has, int(StateFlag.HAS_GOAL), 0)
        | np.where(obs.link_ok[rows], 0, int(StateFlag.FAILSAFE_LINK_LOST))
    )
    flags = [_state_flag(b) for b in bits.tolist()]
    modes = [_MODES[m] for m in core.mode[rows].tolist()]
    vids, seqs = ids[rows].tolist(), seq[rows].tolist()
    armed = obs.armed[rows].tolist()
    battery = np.clip(obs.battery_pct[rows], 0.0, 100.0).tolist()
    sigma = np.clip(pos_sigma_m[rows], 0.0, POS_SIGMA_LIMIT_M).tolist()
    item, items = (x.tolist() for x in core.mission_progress(rows))
    return [
        VehicleState(
            vehicle_id=vids[i],
            seq=seqs[i],
            stamp_ns=stamp_ns,
            pos_ned_m=tuple(pos[i]),
            vel_ned_m_s=tuple(vel[i]),
            heading_rad=hdg[i],
            mode=modes[i],
            armed=armed[i],
            battery_pct=battery[i],
            flags=flags[i],
            goal_ned_m=tuple(goal[i]),
            mission_item=item[i],
            mission_items=items[i],
            pos_sigma_m=sigma[i],
        )
        for i in range(len(vids))
    ]


_TWO_PI = 2 * math.pi
_HAS_GOAL = int(StateFlag.HAS_GOAL)
_LINK_LOST = int(StateFlag.FAILSAFE_LINK_LOST)
_NO_GOAL = (0.0, 0.0, 0.0)


def _one_vehicle_state(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    seq: np.ndarray,
    rows: np.ndarray,
    bits: np.ndarray | int,
    stamp_ns: int,
) -> VehicleState | None:
    """`vehicle_states_rows` of one row, in Python floats: each scalar read once with .item(),
    the heading wrapped with Python's float %, the clamps with min and max (the same IEEE
    operations as np.remainder and np.clip, NaN and -0.0 included: tests compare them). None
    where the inputs are not the plain ones (a float64 heading, float battery and sigma, int
    bits): the general path answers them."""
    try:
        r = rows.item(0)
        plain = (
            core.heading_rad.dtype == F8
            and obs.battery_pct.dtype.kind == "f"
            and pos_sigma_m.dtype.kind == "f"
        )
    except (AttributeError, ValueError):  # not arrays
        return None
    if isinstance(bits, int):
        shell_bits = int(bits)
    elif isinstance(bits, np.ndarray) and bits.dtype.kind in "iub" and bits.ndim == 1:
        shell_bits = int(bits.item(r))
    else:
        return None
    if not plain:
        return None
    target = core.targets()[r].tolist()
    has = target[0] == target[0]  # not NaN: a goal
    run = core.missions[r]
    item, items = (0, 0) if run is None else run.progress()
    battery = min(max(obs.battery_pct.item(r), 0.0), 100.0)
    sigma = min(max(pos_sigma_m.item(r), 0.0), POS_SIGMA_LIMIT_M)
    flags = (
        shell_bits
        | int(core.failsafes[r].flags)
        | (_HAS_GOAL if has else 0)
        | (0 if obs.link_ok.item(r) else _LINK_LOST)
    )
    # built as VehicleState.decode builds one, without the frozen dataclass's __init__ (a
    # setattr per field, half of this state's cost): every field set, equal to the rows' path
    state = object.__new__(VehicleState)
    state.__dict__.update(
        vehicle_id=ids.item(r),
        seq=seq.item(r),
        stamp_ns=stamp_ns,
        pos_ned_m=tuple(obs.pos_m[r].tolist()),
        vel_ned_m_s=tuple(obs.vel_m_s[r].tolist()),
        heading_rad=(core.heading_rad.item(r) + math.pi) % _TWO_PI - math.pi,
        mode=_MODES[core.mode.item(r)],
        armed=obs.armed.item(r),
        battery_pct=battery,
        flags=_state_flag(flags),
        goal_ned_m=tuple(target) if has else _NO_GOAL,
        sig=b"",
        mission_item=int(item),
        mission_items=int(items),
        pos_sigma_m=sigma,
        links=b"",
    )
    return state
