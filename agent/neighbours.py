"""The neighbour table: what this vehicle knows about the others, built from the mesh.

Each entry keeps its receive time. While fresh, a neighbour is dead-reckoned at constant
velocity (p(t) = p + v (t - t_rx)), which hides a 3 Hz link's staleness; past `stale_s` it is
flagged stale (guidance slows down); past `drop_s` it is forgotten. A neighbour whose last
state announces that it holds at rest (comms/state_rate.py `announces_hold`: it publishes only
every MAX_HOLD_PERIOD_S, and at once when it moves) is stale past `hold_stale_s` and forgotten
past `hold_drop_s` instead.
Times are on the agent's clock (receive time), so clock skew between vehicles does not matter.

With a reach (`reach_m`, the scope's: comms/scope.py), the table keeps only the neighbours
within it: the states that the cells within reach bring from beyond it (a 3 x 3 block of 30 m
cells holds several times the reach's disc) are dropped before their signatures are checked
(`worth_checking`, comms/gate.py step 4b), and a neighbour whose verified state says it left
is forgotten. The reach is centred where the vehicle last looked from (`snapshot` with its own
position, every tick).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from comms.schema import Mode, VehicleState
from comms.state_rate import MAX_HOLD_PERIOD_S, announces_hold, hold_rows

_HOLDING = int(Mode.HOLDING)
_GROUNDED = (Mode.LANDED, Mode.KILLED)


@dataclass(frozen=True)
class NeighbourConfig:
    """How long neighbour data stays useful."""

    stale_s: float = 1.0
    """Older than this, a neighbour is stale: guidance slows down near it."""
    drop_s: float = 3.0
    """Older than this, a neighbour is forgotten."""
    hold_stale_s: float = 2.5 * MAX_HOLD_PERIOD_S
    """`stale_s` of a neighbour whose last state announces that it holds at rest (it publishes
    every MAX_HOLD_PERIOD_S): stale after two missed states and half a period for the jitter."""
    hold_drop_s: float = 5.0 * MAX_HOLD_PERIOD_S
    """`drop_s` of a neighbour holding at rest."""

    def __post_init__(self) -> None:
        for name in ("stale_s", "drop_s", "hold_stale_s", "hold_drop_s", "vertical_band_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v}")
        if self.hold_stale_s < MAX_HOLD_PERIOD_S:
            raise ValueError(
                f"hold_stale_s must be at least {MAX_HOLD_PERIOD_S:g} s (a holder publishes that "
                f"often), got {self.hold_stale_s}"
            )

    vertical_band_m: float = 5.0
    """Neighbours more than this far above or below are not traffic (e.g. landed vehicles)."""
    verify_min_interval_s: float = 0.15
    """Keyed mode: a neighbour's state arriving sooner than this after its last accepted one is
    skipped before its signature is checked (about 5 of 10 Hz verified; dead reckoning fills the
    gap). Halves the Ed25519 cost; a forger cannot use it to suppress real states (comms/gate.py)."""


_FILL_DTYPES = {bool: np.dtype(bool), float: np.dtype(float)}
"""np.asarray(fill).dtype of the usual fills."""


@dataclass(frozen=True)
class NeighbourSnapshot:
    pos_ned_m: np.ndarray
    """(K, 3)"""
    vel_ned_m_s: np.ndarray
    """(K, 3)"""
    heading_rad: np.ndarray
    """(K,)"""
    ids: tuple[int, ...]
    age_s: np.ndarray
    stale_ids: tuple[int, ...]
    seqs: tuple[int, ...] = ()
    """The seq of each neighbour's state used (guidance traces for closed-loop replay)."""
    pos_sigma_m: np.ndarray | None = None
    """(K,) the 1-sigma each neighbour reported of its position estimate (VehicleState
    pos_sigma_m); None: all 0. Rows appended without one (traffic) count as 0."""
    cooperative: np.ndarray | None = None
    """(K,) bool: False for a neighbour that does not avoid (traffic, agent/traffic.py): the
    filter takes the whole correction for it. None: all cooperative (covey vehicles)."""
    manned: np.ndarray | None = None
    """(K,) bool: a manned aircraft (traffic only). None: none."""

    def __len__(self) -> int:
        return len(self.ids)

    def column(self, name: str, fill) -> np.ndarray:
        """Per-neighbour column `name` (pos_sigma_m, cooperative, manned) as (K,), its rows
        missing or absent filled with `fill` (a snapshot merged with rows that carry none)."""
        k = len(self.ids)
        got = getattr(self, name)
        dtype = _FILL_DTYPES.get(type(fill))
        if dtype is None:
            dtype = np.asarray(fill).dtype
        if type(got) is np.ndarray and got.shape == (k,) and got.dtype == dtype:
            return got.copy()  # what filling and then overwriting every row leaves
        out = np.full(k, fill, dtype=dtype)
        if got is not None:
            got = np.asarray(got).reshape(-1)[:k]
            out[: len(got)] = got
        return out


class NeighbourTable:
    """Thread-safe: the mesh callback writes, the guidance loop reads."""

    def __init__(
        self,
        own_id: int | None,
        cfg: NeighbourConfig = NeighbourConfig(),
        reach_m: float | None = None,
    ) -> None:
        """`own_id`: the vehicle whose table this is (its own states are ignored); None for a
        host of several vehicles, which keeps its own vehicles out itself. `reach_m`: keep only
        the neighbours within this horizontal distance (module docstring); None: all."""
        if reach_m is not None and not (math.isfinite(reach_m) and reach_m > 0):
            raise ValueError(f"reach_m must be a positive distance in metres, got {reach_m}")
        self.own_id = own_id
        self.cfg = cfg
        self.reach_m = reach_m
        self._centre_ne_m: tuple[float, float] | None = None  # where the reach is centred
        self._lock = threading.Lock()
        self._latest: dict[int, tuple[VehicleState, float]] = {}
        self._version = 0  # bumped by every change of _latest: the snapshot cache's key
        self._cache: tuple | None = None
        self._oldest_s = math.inf
        """No entry was received before this (a lower bound; NaN times left out): `expire`
        looks at the entries only once it is `drop_s` old."""

    def _within_reach(self, pos_ned_m) -> bool:
        centre = self._centre_ne_m
        return (
            self.reach_m is None
            or centre is None
            or math.hypot(pos_ned_m[0] - centre[0], pos_ned_m[1] - centre[1]) <= self.reach_m
        )

    def worth_checking(self, state: VehicleState) -> bool:
        """Whether a state that arrived is worth its signature check: it claims a position within
        reach, or it is from a neighbour the table holds within reach (so that its leaving is
        heard). Judged on the state's own claims and on verified entries only, so a forger can
        get its own states dropped, never another vehicle's (comms/gate.py step 4b)."""
        if self._within_reach(state.pos_ned_m):
            return True
        with self._lock:
            held = self._latest.get(state.vehicle_id)
        return held is not None and self._within_reach(held[0].pos_ned_m)

    def update(self, state: VehicleState, recv_s: float) -> None:
        if state.vehicle_id == self.own_id:
            return
        if not self._within_reach(state.pos_ned_m):  # a verified state: it has left our reach
            self.forget(state.vehicle_id)
            return
        with self._lock:
            prev = self._latest.get(state.vehicle_id)
            # Latest wins, but a reordered older sample must not overwrite a newer one.
            if (
                prev is not None
                and _seq_older(state.seq, prev[0].seq)
                and state.stamp_ns <= prev[0].stamp_ns
            ):
                return
            self._latest[state.vehicle_id] = (state, recv_s)
            self._version += 1
            if recv_s < self._oldest_s:
                self._oldest_s = recv_s

    def forget(self, vehicle_id: int) -> None:
        with self._lock:
            if self._latest.pop(vehicle_id, None) is not None:
                self._version += 1

    def expire(self, now_s: float) -> None:
        """Forget the neighbours unheard for `drop_s` (`snapshot` does it too)."""
        drop_s, hold_drop_s = self.cfg.drop_s, self.cfg.hold_drop_s
        with self._lock:
            if not now_s - self._oldest_s > drop_s:  # nobody is that old (the usual tick)
                return
            for vid in [
                v
                for v, (s, t) in self._latest.items()
                if now_s - t > drop_s
                and (now_s - t > hold_drop_s or not announces_hold(s.mode, s.vel_ned_m_s))
            ]:
                del self._latest[vid]
                self._version += 1
            oldest = math.inf
            for _, t in self._latest.values():
                if t < oldest:
                    oldest = t
            self._oldest_s = oldest

    def snapshot(self, now_s: float, own_pos_ned_m: np.ndarray | None = None) -> NeighbourSnapshot:
        """Neighbours that are flying, fresh enough and in our vertical band (with
        `own_pos_ned_m`), dead-reckoned to now: p(t) = p + v (t - t_rx).

        A few array operations over one block of the table's rows (`_rows`), the block kept
        until the table changes; with `own_pos_ned_m` (one vehicle: an agent), Python floats
        (`_snapshot_around`). `snapshot_loop` is the plain reference; tests compare them. With
        `own_pos_ned_m`, the reach is centred there from now on."""
        if own_pos_ned_m is not None:
            self._centre_ne_m = (float(own_pos_ned_m[0]), float(own_pos_ned_m[1]))
        self.expire(now_s)
        if own_pos_ned_m is not None:
            return self._snapshot_around(now_s, float(own_pos_ned_m[2]))
        with self._lock:
            cached = self._cache
            if cached is None or cached[0] != self._version:
                cached = self._cache = (self._version, self._rows())
        ids, seqs, block, hold = cached[1]
        if not ids:  # an idle vehicle's table (it hears no cells): no array maths at all
            return NeighbourSnapshot(
                pos_ned_m=_EMPTY3.copy(),
                vel_ned_m_s=_EMPTY3.copy(),
                heading_rad=_EMPTY.copy(),
                ids=(),
                age_s=_EMPTY.copy(),
                stale_ids=(),
                seqs=(),
                pos_sigma_m=_EMPTY.copy(),
            )
        # every array below is a new one: the cached block stays as it is
        age = np.maximum(0.0, now_s - block[:, 8])
        pos = block[:, 0:3] + block[:, 3:6] * age[:, None]
        keep = None
        if own_pos_ned_m is not None:
            keep = np.abs(pos[:, 2] - float(own_pos_ned_m[2])) <= self.cfg.vertical_band_m
            if np.count_nonzero(keep) == len(ids):
                keep = None
        if keep is None:
            vel, hdg, sigma = block[:, 3:6].copy(), block[:, 6].copy(), block[:, 7].copy()
        else:
            idx = keep.nonzero()[0].tolist()
            ids = tuple([ids[i] for i in idx])
            seqs = tuple([seqs[i] for i in idx])
            pos, age, vel, hdg, sigma = (
                pos[keep],
                age[keep],
                block[keep, 3:6],
                block[keep, 6],
                block[keep, 7],
            )
            if hold is not None:
                hold = hold[keep]
        cfg = self.cfg
        over = age > (
            cfg.stale_s if hold is None else np.where(hold, cfg.hold_stale_s, cfg.stale_s)
        )
        stale = (
            tuple([ids[i] for i in over.nonzero()[0].tolist()]) if np.count_nonzero(over) else ()
        )
        return NeighbourSnapshot(
            pos_ned_m=pos,
            vel_ned_m_s=vel,
            heading_rad=hdg,
            ids=ids,
            age_s=age,
            stale_ids=stale,
            seqs=seqs,
            pos_sigma_m=sigma,
        )

    def _snapshot_around(self, now_s: float, own_d_m: float) -> NeighbourSnapshot:
        """`snapshot` around one vehicle at depth `own_d_m` (an agent's every tick): its
        neighbours dead-reckoned one by one on Python floats, then five arrays made of them
        (a tenth of the array calls of the block's path; equal to `snapshot_loop`,
        tests/test_neighbour_table.py). Expired entries already gone."""
        cfg = self.cfg
        band_m, stale_s, hold_stale_s = cfg.vertical_band_m, cfg.stale_s, cfg.hold_stale_s
        with self._lock:
            items = list(self._latest.values())
        pos: list[float] = []
        vel: list[float] = []
        hdg: list[float] = []
        sigma: list[float] = []
        ages: list[float] = []
        ids: list[int] = []
        seqs: list[int] = []
        stale: list[int] = []
        for s, t in items:
            if s.mode in _GROUNDED and not s.armed:
                continue
            age_s = now_s - t
            if age_s < 0.0:
                age_s = 0.0
            (pn, pe, pd), v = s.pos_ned_m, s.vel_ned_m_s
            vn, ve, vd = v
            pd = pd + vd * age_s
            if abs(pd - own_d_m) > band_m:
                continue
            pos += (pn + vn * age_s, pe + ve * age_s, pd)
            vel += v
            hdg.append(s.heading_rad)
            sigma.append(s.pos_sigma_m)
            ages.append(age_s)
            ids.append(s.vehicle_id)
            seqs.append(s.seq)
            if age_s > (hold_stale_s if announces_hold(s.mode, v) else stale_s):
                stale.append(s.vehicle_id)
        k = len(ids)
        return NeighbourSnapshot(
            pos_ned_m=np.array(pos, float).reshape(k, 3),
            vel_ned_m_s=np.array(vel, float).reshape(k, 3),
            heading_rad=np.array(hdg, float),
            ids=tuple(ids),
            age_s=np.array(ages, float),
            stale_ids=tuple(stale),
            seqs=tuple(seqs),
            pos_sigma_m=np.array(sigma, float),
        )

    def _rows(self) -> tuple:
        """(ids, seqs, block, hold) of the flying neighbours (lock held): block (K, 9) holds
        each one's position, velocity, heading, position 1-sigma and receive time; hold (K,)
        which announce that they hold at rest, None: none does."""
        flat: list = []  # the block's rows one after the other: one conversion for them all
        meta: list = []  # (id, seq, mode) of each
        for s, t in self._latest.values():
            if s.mode in _GROUNDED and not s.armed:
                continue
            flat += (*s.pos_ned_m, *s.vel_ned_m_s, s.heading_rad, s.pos_sigma_m, t)
            meta += (s.vehicle_id, s.seq, s.mode)
        k = len(meta) // 3
        if k == 0:
            return (), (), None, None
        block = np.fromiter(flat, float, 9 * k).reshape(k, 9)
        block.flags.writeable = False  # shared by the snapshots: each takes new arrays of it
        modes = meta[2::3]
        hold = None
        if _HOLDING in modes:  # the velocities as one contiguous (K, 3), as hold_rows sums them
            hold = hold_rows([int(m) for m in modes], block[:, 3:6].copy())
        return tuple(meta[0::3]), tuple(meta[1::3]), block, hold

    def snapshot_loop(
        self, now_s: float, own_pos_ned_m: np.ndarray | None = None
    ) -> NeighbourSnapshot:
        """The reference for `snapshot`: the same result, one neighbour at a time."""
        self.expire(now_s)
        with self._lock:
            items = list(self._latest.values())
        pos, vel, hdg, ids, ages, stale, seqs, sigma = [], [], [], [], [], [], [], []
        for state, recv_s in items:
            if state.mode in (Mode.LANDED, Mode.KILLED) and not state.armed:
                continue
            age_s = max(0.0, now_s - recv_s)
            p = np.asarray(state.pos_ned_m, dtype=float) + np.asarray(state.vel_ned_m_s) * age_s
            if (
                own_pos_ned_m is not None
                and abs(p[2] - own_pos_ned_m[2]) > self.cfg.vertical_band_m
            ):
                continue
            pos.append(p)
            vel.append(state.vel_ned_m_s)
            hdg.append(state.heading_rad)
            ids.append(state.vehicle_id)
            seqs.append(state.seq)
            sigma.append(state.pos_sigma_m)
            ages.append(age_s)
            hold = announces_hold(state.mode, state.vel_ned_m_s)
            if age_s > (self.cfg.hold_stale_s if hold else self.cfg.stale_s):
                stale.append(state.vehicle_id)
        k = len(ids)
        return NeighbourSnapshot(
            pos_ned_m=np.array(pos, dtype=float).reshape(k, 3),
            vel_ned_m_s=np.array(vel, dtype=float).reshape(k, 3),
            heading_rad=np.array(hdg, dtype=float).reshape(k),
            ids=tuple(ids),
            age_s=np.array(ages, dtype=float).reshape(k),
            stale_ids=tuple(stale),
            seqs=tuple(seqs),
            pos_sigma_m=np.array(sigma, dtype=float).reshape(k),
        )

    def latest(self) -> dict[int, VehicleState]:
        with self._lock:
            return {vid: s for vid, (s, _) in self._latest.items()}


_EMPTY = np.zeros(0)
_EMPTY3 = np.zeros((0, 3))
for _a in (_EMPTY, _EMPTY3):
    _a.flags.writeable = False  # shared by every empty snapshot (which copies them anyway)


def _seq_older(a: int, b: int) -> bool:
    """True if 32-bit sequence number a comes before b (serial-number arithmetic, RFC 1982)."""
    return a != b and ((b - a) & 0xFFFFFFFF) < 0x80000000
