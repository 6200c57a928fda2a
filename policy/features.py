"""Numpy reference of the policy observation (docs/POLICY_SPEC.md).

Everything here is in policy units (3 m separation at 1 m/s). The onboard C core and
the torch trainer follow this module; `observe` is the single-vehicle reference,
`observe_batch` the vectorised form used by the environment and `command_batch`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

TWO_PI = 2.0 * np.pi
ENCODINGS = ("paper", "sincos")
ORDERS = ("index", "closest_last")


@dataclass(frozen=True)
class ObsConfig:
    """How a vehicle turns its neighbours and goal into network inputs."""

    encoding: str = "paper"
    """"paper" ([d, psi_ij, |psi_ji|], goal [psi_D]) or "sincos" (angles as sin, cos)."""
    order: str = "index"
    """"index" keeps the given order; "closest_last" feeds the nearest neighbour last."""
    dist_scale: float = 1.0
    """Distances are divided by this (policy units); 1.0 in the paper configuration."""
    sense_range: float = 0.0
    """Neighbours farther than this (policy units) are dropped; 0 means unlimited."""

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        if self.order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {self.order!r}")
        if not (self.dist_scale > 0 and np.isfinite(self.dist_scale)):
            raise ValueError(f"dist_scale must be finite and > 0, got {self.dist_scale}")
        if not (self.sense_range >= 0 and np.isfinite(self.sense_range)):
            raise ValueError(f"sense_range must be finite and >= 0, got {self.sense_range}")

    @property
    def input_size(self) -> int:
        """Width of one neighbour tuple."""
        return 3 if self.encoding == "paper" else 5

    @property
    def goal_size(self) -> int:
        """Width of the goal features."""
        return 1 if self.encoding == "paper" else 2

    @classmethod
    def from_dict(cls, cfg: dict) -> ObsConfig:
        """Reads the observation fields of a weights-file config (others are ignored)."""
        return cls(
            encoding=str(cfg.get("encoding", "paper")),
            order=str(cfg.get("order", "index")),
            dist_scale=float(cfg.get("dist_scale", 1.0)),
            sense_range=float(cfg.get("sense_range", 0.0) or 0.0),
        )

    def to_dict(self) -> dict:
        return asdict(self)


def wrap_rad(angle_rad):
    """Wraps to [-pi, pi): wrap(a) = ((a + pi) mod 2 pi) - pi."""
    return np.mod(np.asarray(angle_rad, dtype=np.float64) + np.pi, TWO_PI) - np.pi


def neighbour_tuples(pos, heading_rad, nbr_pos, nbr_heading_rad):
    """Returns (d_ij, psi_ij, psi_ji) for each neighbour, each shape (K,)."""
    rel = np.asarray(nbr_pos, dtype=np.float64) - np.asarray(pos, dtype=np.float64)
    d = np.hypot(rel[:, 0], rel[:, 1])
    los_ij = np.arctan2(rel[:, 1], rel[:, 0])
    psi_ij = wrap_rad(los_ij - heading_rad)
    # line of sight j -> i is the opposite direction: atan2(-dy, -dx)
    psi_ji = wrap_rad(
        np.asarray(nbr_heading_rad, dtype=np.float64) - np.arctan2(-rel[:, 1], -rel[:, 0])
    )
    return d, psi_ij, psi_ji


def select_order(d, cfg: ObsConfig, max_neighbours: int | None = None) -> np.ndarray:
    """Indices of the neighbours to feed, in feeding order.

    Drops those beyond sense_range, keeps the nearest max_neighbours (ties: given
    order), then orders by index or by decreasing distance (stable).
    """
    d = np.asarray(d, dtype=np.float64)
    idx = np.arange(d.shape[0])
    if cfg.sense_range > 0:
        idx = idx[d <= cfg.sense_range]
    if max_neighbours is not None and idx.shape[0] > max_neighbours:
        idx = idx[np.argsort(d[idx], kind="stable")[:max_neighbours]]
        idx = np.sort(idx)
    if cfg.order == "closest_last":
        idx = idx[np.argsort(-d[idx], kind="stable")]
    return idx


def encode_tuples(d, psi_ij, psi_ji, cfg: ObsConfig) -> np.ndarray:
    """Stacks neighbour tuples into LSTM inputs, shape (..., X)."""
    ds = np.asarray(d) / cfg.dist_scale
    if cfg.encoding == "paper":
        return np.stack([ds, psi_ij, np.abs(psi_ji)], axis=-1)
    return np.stack([ds, np.sin(psi_ij), np.cos(psi_ij), np.sin(psi_ji), np.cos(psi_ji)], axis=-1)


def goal_features(pos, heading_rad, goal, cfg: ObsConfig) -> np.ndarray:
    """[psi_D] or [sin psi_D, cos psi_D], shape (..., G)."""
    pos = np.asarray(pos, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)
    psi_d = wrap_rad(
        np.arctan2(goal[..., 1] - pos[..., 1], goal[..., 0] - pos[..., 0]) - heading_rad
    )
    if cfg.encoding == "paper":
        return psi_d[..., None]
    return np.stack([np.sin(psi_d), np.cos(psi_d)], axis=-1)


def observe(pos, heading_rad, goal, nbr_pos, nbr_heading_rad, cfg: ObsConfig, max_neighbours=None):
    """Single-vehicle observation: (sequence (L, X), goal features (G,), chosen indices (L,))."""
    nbr_pos = np.asarray(nbr_pos, dtype=np.float64).reshape(-1, 2)
    d, psi_ij, psi_ji = neighbour_tuples(pos, heading_rad, nbr_pos, nbr_heading_rad)
    idx = select_order(d, cfg, max_neighbours)
    seq = encode_tuples(d[idx], psi_ij[idx], psi_ji[idx], cfg)
    return seq.reshape(-1, cfg.input_size), goal_features(pos, heading_rad, goal, cfg), idx


def observe_fast(
    pos, heading_rad, goal, nbr_pos, nbr_heading_rad, cfg: ObsConfig, max_neighbours=None
):
    """`observe` with fewer numpy calls (the per-vehicle runtime's hot path); equal within
    1e-12 (tests/test_policy_speed.py). Relative positions as complex numbers z = r_n + i r_e:
      e^{i psi_ij} = (z / |z|) e^{-i h_i},   e^{i psi_ji} = -e^{i h_j} conj(z / |z|)
    (psi_ji = h_j - los - pi), so the sines and cosines need no atan2 and no wrap.
    Falls back to `observe` for the paper encoding and for a neighbour exactly on top."""
    nbr_pos = np.asarray(nbr_pos, dtype=np.float64).reshape(-1, 2)
    if cfg.encoding != "sincos":
        return observe(pos, heading_rad, goal, nbr_pos, nbr_heading_rad, cfg, max_neighbours)
    z = (nbr_pos - pos).view(np.complex128)[:, 0]
    d = np.abs(z)
    k = d.shape[0]
    if cfg.order == "closest_last" and (max_neighbours is None or k <= max_neighbours):
        # one stable sort by decreasing distance; the sense range cut keeps that order
        idx = np.argsort(-d, kind="stable")
        if k and not d[idx[-1]] > 0.0:  # the nearest (a NaN sorts last too)
            return observe(pos, heading_rad, goal, nbr_pos, nbr_heading_rad, cfg, max_neighbours)
        if cfg.sense_range > 0:
            idx = idx[d[idx] <= cfg.sense_range]
    else:
        if k and not d.min() > 0.0:
            return observe(pos, heading_rad, goal, nbr_pos, nbr_heading_rad, cfg, max_neighbours)
        idx = select_order(d, cfg, max_neighbours)
    d, z = d[idx], z[idx]
    u = z / d
    seq = np.empty((idx.shape[0], 5))
    seq[:, 0] = d / cfg.dist_scale
    h = float(heading_rad)
    e_ij = u * complex(math.cos(h), -math.sin(h))
    e_ji = np.exp(1j * np.asarray(nbr_heading_rad, dtype=np.float64)[idx]) * u.conj()
    # columns 2, 1 <- (real, imag) = (cos, sin); 4, 3 likewise, e_ji negated
    seq[:, 2:0:-1] = e_ij.view(np.float64).reshape(-1, 2)
    np.negative(e_ji.view(np.float64).reshape(-1, 2), out=seq[:, 4:2:-1])
    g_n, g_e = float(goal[0]) - float(pos[0]), float(goal[1]) - float(pos[1])
    psi_d = math.atan2(g_e, g_n) - h
    return seq, np.array([math.sin(psi_d), math.cos(psi_d)]), idx


class RowsTable:
    """Scratch of `closest_last_rows` for up to `rows` neighbours: a (rows, 3) complex128 table
    (float64 writes cost half of a cast into complex64) whose column 0 has imaginary part 1
    (it stays so), with views of its columns."""

    def __init__(self, rows: int):
        self.rows = rows
        self.table = np.zeros((rows, 3), np.complex128)
        self.table[:, 0].imag = 1.0
        self.d = self.table[:, 0].real
        self.e_ij = self.table[:, 1]
        self.e_ji = self.table[:, 2]


_C128 = np.dtype(np.complex128)


def closest_last_rows(rel, heading_rad: float, nbr_heading_rad, sense_range: float, scratch):
    """The sincos / closest_last neighbour inputs as complex rows, for a projection that takes
    them as they come (the one-vehicle runtime's hot path; `rows_as_seq` turns them into
    `observe`'s sequence, equal within float32 rounding, tests/test_policy_speed.py).

    rel (K, 2): neighbour minus own position, C-contiguous float64, in any length unit;
    sense_range in that unit (0 = unlimited, as ObsConfig.sense_range); scratch: a RowsTable
    of >= K rows. Returns (rows (L, 3) complex64, chosen indices (L,)) in feeding order
    (decreasing distance, ties in given order), each row [d + 1j, e^{i psi_ij},
    -conj(e^{i psi_ji})], i.e. as six floats [d, 1, cos psi_ij, sin psi_ij, -cos psi_ji,
    sin psi_ji] (the 1: room for a bias); or None when a neighbour sits exactly on top or a
    distance is not finite (the caller then takes `observe`). With u = z / |z| (z = rel as
    r_n + i r_e): e^{i psi_ij} = u e^{-i h_i} and -conj(e^{i psi_ji}) = u / e^{i h_j}, as in
    `observe_fast`. Numpy calls are few: methods (not np.* wrappers), one gather (take), the
    cast to complex64 (float32, the network's precision) last.
    """
    z = rel.view(_C128).ravel()
    d = np.abs(z)
    order = (-d).argsort(kind="stable")
    k = d.shape[0]
    if k:
        d_l, o_l = d.tolist(), order.tolist()
        far = d_l[o_l[0]]
        if not (d_l[o_l[-1]] > 0.0 and far < math.inf):  # NaN sorts last
            return None
        if 0.0 < sense_range < far:  # the farthest come first: cut them
            cut = 1
            while cut < k and d_l[o_l[cut]] > sense_range:
                cut += 1
            order = order[cut:]
        scratch.d[:k] = d
        u = z / d
        np.multiply(u, complex(math.cos(heading_rad), -math.sin(heading_rad)), scratch.e_ij[:k])
        e_j = np.zeros(k, _C128)
        e_j.imag = nbr_heading_rad
        np.exp(e_j, e_j)
        np.divide(u, e_j, scratch.e_ji[:k])
    return scratch.table.take(order, 0).astype(np.complex64), order


def rows_as_seq(rows, dist_scale: float) -> np.ndarray:
    """`closest_last_rows`' rows as `observe`'s sincos sequence (L, 5), float64."""
    x = np.asarray(rows).astype(np.complex128)
    return np.stack(
        [x[:, 0].real / dist_scale, x[:, 1].imag, x[:, 1].real, x[:, 2].imag, -x[:, 2].real],
        axis=-1,
    )


def observe_batch(pos, heading_rad, goal, active, cfg: ObsConfig, max_neighbours=None):
    """Every active vehicle observes every other active vehicle of its world.

    pos (..., N, 2), heading_rad (..., N), goal (..., N, 2), active (..., N) bool;
    leading dimensions are separate worlds (the env's environments).
    Returns seq (..., N, K, X) zero padded after each row's length, lengths (..., N),
    goal features (..., N, G) and neighbour indices (..., N, K) (-1 = padding).
    Selection and order match `observe` (ties at the max_neighbours cut aside).
    """
    pos = np.asarray(pos, dtype=np.float64)
    heading_rad = np.asarray(heading_rad, dtype=np.float64)
    active = np.asarray(active, dtype=bool)
    n = pos.shape[-2]
    # squared distances key[..., i, j]; self, inactive and out-of-range pairs are inf
    dx = pos[..., None, :, 0] - pos[..., :, None, 0]
    dy = pos[..., None, :, 1] - pos[..., :, None, 1]
    key = dx * dx + dy * dy
    del dx, dy
    ar = np.arange(n)
    key[..., ar, ar] = np.inf
    key += np.where(active, 0.0, np.inf)[..., None, :]
    if cfg.sense_range > 0:
        key[key > cfg.sense_range**2] = np.inf
    k = max(n - 1 if max_neighbours is None else min(max_neighbours, n - 1), 0)
    # nearest k, ties broken by index (= stable); a full sort only when cheap
    if 0 < k < n - 1 and n > 64:
        part = np.argpartition(key, k - 1, axis=-1)[..., :k]
        o = np.lexsort((part, np.take_along_axis(key, part, axis=-1)), axis=-1)
        nearest = np.take_along_axis(part, o, axis=-1)
    else:
        nearest = np.argsort(key, axis=-1, kind="stable")[..., :k]
    nd = np.take_along_axis(key, nearest, axis=-1)
    ok = np.isfinite(nd) & active[..., None]
    lengths = ok.sum(axis=-1)
    if cfg.order == "index":
        o = np.argsort(np.where(ok, nearest, n + 1), axis=-1, kind="stable")
    else:
        # decreasing distance, ties in index order; padding (inf) goes last
        o = np.lexsort((nearest, np.where(ok, -nd, np.inf)), axis=-1)
    nbr = np.take_along_axis(nearest, o, axis=-1)
    ok = np.take_along_axis(ok, o, axis=-1)
    nbr = np.where(ok, nbr, -1)
    # gather the K neighbours of each row: (..., N, K)
    pos_nbr = np.take_along_axis(pos[..., None, :, :], np.maximum(nbr, 0)[..., None], axis=-2)
    h_nbr = np.take_along_axis(heading_rad[..., None, :], np.maximum(nbr, 0), axis=-1)
    rx = pos_nbr[..., 0] - pos[..., :, None, 0]
    ry = pos_nbr[..., 1] - pos[..., :, None, 1]
    los = np.arctan2(ry, rx)
    psi_ij = wrap_rad(los - heading_rad[..., None])
    psi_ji = wrap_rad(h_nbr - (los + np.pi))  # the line of sight j -> i is los + pi
    seq = encode_tuples(np.hypot(rx, ry), psi_ij, psi_ji, cfg) * ok[..., None]
    return seq, lengths, goal_features(pos, heading_rad, goal, cfg), nbr


def observe_padded(
    pos, heading_rad, goal, nbr_pos, nbr_heading_rad, nbr_valid, cfg: ObsConfig, max_neighbours=None
):
    """Each vehicle with its own neighbour list (e.g. what its radio link delivered).

    pos (N,2), heading_rad (N,), goal (N,2); nbr_pos (N,K,2), nbr_heading_rad (N,K),
    nbr_valid (N,K) bool. Returns seq (N,K',X), lengths (N,), goal features (N,G) and
    the chosen columns (N,K') (-1 = padding), as `observe` row by row.
    """
    pos = np.asarray(pos, dtype=np.float64)
    nbr_pos = np.asarray(nbr_pos, dtype=np.float64)
    heading_rad = np.asarray(heading_rad, dtype=np.float64)
    n, kk = nbr_valid.shape
    rx = nbr_pos[..., 0] - pos[:, None, 0]
    ry = nbr_pos[..., 1] - pos[:, None, 1]
    d = np.hypot(rx, ry)
    valid = np.asarray(nbr_valid, dtype=bool).copy()
    if cfg.sense_range > 0:
        valid &= d <= cfg.sense_range
    key = np.where(valid, d, np.inf)
    k = kk if max_neighbours is None else min(max_neighbours, kk)
    cols = np.arange(kk)
    nearest = np.lexsort((np.broadcast_to(cols, key.shape), key), axis=-1)[:, :k]
    nd = np.take_along_axis(key, nearest, axis=-1)
    ok = np.isfinite(nd)
    if cfg.order == "index":
        o = np.argsort(np.where(ok, nearest, kk + 1), axis=-1, kind="stable")
    else:
        o = np.lexsort((nearest, np.where(ok, -nd, np.inf)), axis=-1)
    sel = np.take_along_axis(nearest, o, axis=-1)
    ok = np.take_along_axis(ok, o, axis=-1)
    sx, sy = np.take_along_axis(rx, sel, -1), np.take_along_axis(ry, sel, -1)
    los = np.arctan2(sy, sx)
    psi_ij = wrap_rad(los - heading_rad[:, None])
    psi_ji = wrap_rad(
        np.take_along_axis(np.asarray(nbr_heading_rad, np.float64), sel, -1) - (los + np.pi)
    )
    seq = encode_tuples(np.hypot(sx, sy), psi_ij, psi_ji, cfg) * ok[..., None]
    return seq, ok.sum(-1), goal_features(pos, heading_rad, goal, cfg), np.where(ok, sel, -1)


def action_to_velocity(action, heading_rad):
    """Body-frame action (fwd, right) to (north, east) velocity in policy units.

    v_n = a_f cos h - a_r sin h,  v_e = a_f sin h + a_r cos h
    """
    a = np.asarray(action, dtype=np.float64)
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.stack([a[..., 0] * c - a[..., 1] * s, a[..., 0] * s + a[..., 1] * c], axis=-1)


def velocity_to_action(vel, heading_rad):
    """Inverse of action_to_velocity."""
    v = np.asarray(vel, dtype=np.float64)
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.stack([v[..., 0] * c + v[..., 1] * s, -v[..., 0] * s + v[..., 1] * c], axis=-1)


def clip_unit(action):
    """a / |a| where |a| > 1 (the spec's clip to unit length)."""
    a = np.asarray(action, dtype=np.float64)
    n = np.hypot(a[..., 0], a[..., 1])
    return a / np.maximum(n, 1.0)[..., None]
