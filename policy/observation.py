"""What a vehicle sees, as one value: the runtime's, the C core's and the filter's input.

    obs = Observation.checked(pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s,
                              nbr_heading_rad, pos_sigma_m=0.0, nbr_pos_sigma_m=None,
                              nbr_cooperative=None)

`Observation` is one vehicle and its K neighbours; `Observations` is N vehicles, each with its
own padded view of the others (what each link delivered); `Swarm` is N vehicles that all see
every other active one (a simulation's true state). `checked` is the boundary: it names the
input that is wrong (a ValueError) and passes already-good float64 arrays through uncopied.

World frame: x north, y east, metres; heading 0 = north, clockwise positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

_F64 = np.dtype(np.float64)
_INF = math.inf


def check_array(name: str, x, shape: tuple, finite: bool = True) -> np.ndarray:
    """Array of the given shape (-1 = any length), finite (unless `finite` is False: the
    caller checks with `check_finite`), or a ValueError saying which."""
    if type(x) is np.ndarray and x.dtype is _F64:
        a = x  # the common case, without asarray's dispatch
    else:
        try:
            a = np.asarray(x, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name} must be numeric, got {type(x).__name__}") from e
    got = a.shape
    if got != shape and (
        len(got) != len(shape) or any(s != -1 and s != d for s, d in zip(shape, got, strict=True))
    ):
        want = "(" + ", ".join("K" if s == -1 else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {got}")
    if finite and not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite, got {a!r}")
    return a


def check_finite(**arrays) -> None:
    """One isfinite over all of them (the hot path); on a failure, the named ValueError."""
    if not np.isfinite(np.concatenate([np.ravel(a) for a in arrays.values()])).all():
        for name, a in arrays.items():
            if not np.isfinite(a).all():
                raise ValueError(f"{name} must be finite, got {a!r}")


@dataclass(frozen=True)
class Sky:
    """The filter's real-vehicle inputs (policy.safety.pair_radius_m): defaults fly exact
    positions among cooperative neighbours."""

    pos_sigma_m: float = 0.0
    """The own position estimate's 1-sigma, metres per axis (PX4's eph)."""
    nbr_pos_sigma_m: np.ndarray | None = None
    """(K,) the neighbours' 1-sigma as they reported them; None: exact."""
    nbr_cooperative: np.ndarray | None = None
    """(K,) bool, False for a neighbour that does not avoid (traffic); None: all cooperate."""
    nbr_manned: np.ndarray | None = None
    """(K,) bool, True for a manned aircraft (traffic the filter keeps its own, wider berth
    from: SafetyConfig.manned_radius_m; it never cooperates, whatever nbr_cooperative says);
    None: none."""

    @classmethod
    def checked(
        cls,
        pos_sigma_m=0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        k: int = -1,
        nbr_manned=None,
    ):
        """pos_sigma_m a finite float >= 0, nbr_pos_sigma_m (k,) finite >= 0 or None,
        nbr_cooperative and nbr_manned (k,) bool or None (k = -1: any length, checked later
        against the neighbours: `fit`); a ValueError naming the bad one. All defaults: EXACT."""
        if (
            not pos_sigma_m
            and nbr_pos_sigma_m is None
            and nbr_cooperative is None
            and nbr_manned is None
        ):
            return EXACT
        try:
            own = float(pos_sigma_m)
        except (TypeError, ValueError):
            raise ValueError(f"pos_sigma_m must be a number, got {pos_sigma_m!r}") from None
        if not (math.isfinite(own) and own >= 0.0):
            raise ValueError(f"pos_sigma_m must be finite and >= 0, got {own}")
        sig = None
        if nbr_pos_sigma_m is not None:
            sig = check_array("nbr_pos_sigma_m", nbr_pos_sigma_m, (k,))
            if (sig < 0).any():
                raise ValueError(f"nbr_pos_sigma_m must be >= 0, got {sig!r}")
        coop = _flags("nbr_cooperative", nbr_cooperative, k)
        manned = _flags("nbr_manned", nbr_manned, k)
        return cls(own, sig, coop, manned)

    def fit(self, k: int) -> Sky:
        """This sky for k neighbours: a scalar sigma or flag stands for all of them (the C
        core's callers pass one); another length is a ValueError naming it."""
        if self is EXACT:
            return self
        sig = self.nbr_pos_sigma_m
        if sig is not None:
            sig = np.asarray(sig, dtype=np.float64)
            if sig.ndim == 0:
                sig = np.full(k, float(sig))
            elif sig.shape != (k,):
                raise ValueError(f"nbr_pos_sigma_m must have shape ({k},), got {sig.shape}")
        coop = _fit_flags("nbr_cooperative", self.nbr_cooperative, k)
        manned = _fit_flags("nbr_manned", self.nbr_manned, k)
        return Sky(float(self.pos_sigma_m), sig, coop, manned)

    def kwargs(self) -> dict:
        """As policy.safety's and policy.sparse's keyword arguments (nbr_manned only when
        some neighbour is flagged: the filters take it, and it is None in the common case)."""
        out = {
            "pos_sigma_m": self.pos_sigma_m,
            "nbr_pos_sigma_m": self.nbr_pos_sigma_m,
            "nbr_cooperative": self.nbr_cooperative,
        }
        if self.nbr_manned is not None:
            out["nbr_manned"] = self.nbr_manned
        return out

    def nbr_sigma_max_m(self) -> float:
        """The largest 1-sigma of the cooperative neighbours (covey's vehicles: traffic and
        manned aircraft left out), 0 without any (policy.runtime.told_scale)."""
        sig = self.nbr_pos_sigma_m
        if sig is None or not len(sig):
            return 0.0
        keep = _cooperative(len(sig), self.nbr_cooperative, self.nbr_manned)
        return float(np.fmax.reduce(sig[keep], initial=0.0))  # fmax passes over a NaN

    def rows(self, keep) -> Sky:
        """These uncertainties for the neighbours `keep` selects (a mask or indices)."""
        sig, coop, manned = self.nbr_pos_sigma_m, self.nbr_cooperative, self.nbr_manned
        return Sky(
            self.pos_sigma_m,
            None if sig is None else sig[keep],
            None if coop is None else coop[keep],
            None if manned is None else manned[keep],
        )


def _cooperative(shape, cooperative, manned) -> np.ndarray:
    """bool mask of the neighbours that cooperate and are not manned (None flags: all do)."""
    keep = np.ones(shape, bool)
    if cooperative is not None:
        keep &= np.asarray(cooperative, bool)
    if manned is not None:
        keep &= ~np.asarray(manned, bool)
    return keep


def _flags(name: str, x, k: int) -> np.ndarray | None:
    """(k,) bool flags (k = -1: any length) from booleans or 0/1, or None; a ValueError naming
    `name` otherwise."""
    if x is None:
        return None
    a = np.asarray(x)
    if a.ndim != 1 or (k >= 0 and a.shape != (k,)):
        raise ValueError(f"{name} must have shape (K,) = ({k},), got {a.shape}")
    if a.dtype != bool and not np.isin(a, (0, 1)).all():
        raise ValueError(f"{name} must be booleans")
    return a.astype(bool)


def _fit_flags(name: str, x, k: int) -> np.ndarray | None:
    """Flags for k neighbours: a scalar stands for all of them."""
    if x is None:
        return None
    a = np.asarray(x)
    if a.ndim == 0:
        return np.full(k, bool(a))
    if a.shape != (k,):
        raise ValueError(f"{name} must have shape ({k},), got {a.shape}")
    return a.astype(bool)


EXACT = Sky()
"""Exact positions, every neighbour cooperative."""


def _pair(x) -> np.ndarray | None:
    """A (2,) float64 array as it is, or a list / tuple of two Python floats as one; None for
    anything else (the checked path then says what is wrong)."""
    if type(x) is np.ndarray:
        return x if x.dtype is _F64 and x.shape == (2,) else None
    if type(x) in (list, tuple) and len(x) == 2 and type(x[0]) is float and type(x[1]) is float:
        return np.array(x)
    return None


def _rows_f64(x, shape: tuple) -> bool:
    """x is a float64 array of exactly this shape."""
    return type(x) is np.ndarray and x.dtype is _F64 and x.shape == shape


class Observation(NamedTuple):
    """One vehicle and its K neighbours, world units. Named arrays (a NamedTuple: immutable,
    and built on every `command`, where a frozen dataclass's __init__ costs a few µs more)."""

    pos_m: np.ndarray
    """(2,) own position (north, east)."""
    vel_m_s: np.ndarray
    """(2,) own velocity."""
    heading_rad: float
    """Own heading, 0 = north, clockwise positive."""
    goal_m: np.ndarray
    """(2,) where to fly (the route's next waypoint once a policy with zones routed it)."""
    nbr_pos_m: np.ndarray
    """(K, 2) neighbour positions."""
    nbr_vel_m_s: np.ndarray
    """(K, 2) neighbour velocities."""
    nbr_heading_rad: np.ndarray
    """(K,) neighbour headings."""
    sky: Sky = EXACT
    """Position uncertainties and cooperative flags for the filter."""

    @classmethod
    def checked(
        cls, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky=EXACT
    ) -> Observation:
        """The observation of these inputs, or a ValueError naming the one that is wrong
        (shape, type, a non-finite value anywhere). float64 arrays of the right shapes (a
        2-vector may also be a list of two floats, the heading a float) pass uncopied. `sky`:
        Sky.checked's, fitted to the neighbours here."""
        obs = cls._fast(
            pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad
        )
        if obs is None:
            obs = cls._converted(
                pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad
            )
        return obs if sky is EXACT else obs._replace(sky=sky.fit(obs.nbr_pos_m.shape[0]))

    @classmethod
    def shaped(
        cls, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky=EXACT
    ) -> Observation:
        """float64 arrays in the right shapes with the values unchecked: for the C core, which
        checks them itself and reports a fault (firmware.cpolicy, firmware.csafety). A
        ValueError names what does not fit."""
        nbr_pos = np.asarray(nbr_pos_m, dtype=np.float64).reshape(-1, 2)
        k = nbr_pos.shape[0]
        nbr_h = np.asarray(nbr_heading_rad, dtype=np.float64).reshape(-1)
        if nbr_h.shape[0] != k:
            raise ValueError(f"nbr_heading_rad has {nbr_h.shape[0]} entries for {k} neighbours")
        nbr_vel = np.asarray(nbr_vel_m_s, dtype=np.float64).reshape(-1, 2)
        if nbr_vel.shape != nbr_pos.shape:
            raise ValueError(f"{k} neighbour positions but {nbr_vel.shape[0]} velocities")
        return cls(
            np.asarray(pos_m, dtype=np.float64).reshape(2),
            np.asarray(vel_m_s, dtype=np.float64).reshape(2),
            float(heading_rad),
            np.asarray(goal_m, dtype=np.float64).reshape(2),
            nbr_pos,
            nbr_vel,
            nbr_h,
            sky.fit(k),
        )

    @classmethod
    def at_rest(cls, pos_m, heading_rad, goal_m, nbr_pos_m, nbr_heading_rad) -> Observation:
        """`checked` with every vehicle standing still: what the network reads (it takes no
        velocities), for tests and benchmarks of the action alone."""
        k = np.shape(nbr_pos_m)[0] if np.ndim(nbr_pos_m) == 2 else 0
        return cls.checked(
            pos_m, np.zeros(2), heading_rad, goal_m, nbr_pos_m, np.zeros((k, 2)), nbr_heading_rad
        )

    @classmethod
    def _fast(cls, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad):
        """The common case (float64 arrays of the right shapes, all finite) without a copy;
        None for anything else. Finite: (x - x) is 0 for a finite float and NaN otherwise;
        x.x over an array is finite exactly when its entries are (or it overflows: then the
        converted path, which looks entry by entry)."""
        if type(nbr_pos_m) is not np.ndarray or nbr_pos_m.ndim != 2:
            return None
        k = nbr_pos_m.shape[0]
        pos, vel, goal = _pair(pos_m), _pair(vel_m_s), _pair(goal_m)
        if (
            pos is None
            or vel is None
            or goal is None
            or not isinstance(heading_rad, float)
            or not _rows_f64(nbr_pos_m, (k, 2))
            or not _rows_f64(nbr_vel_m_s, (k, 2))
            or not _rows_f64(nbr_heading_rad, (k,))
        ):
            return None
        h = float(heading_rad)
        (p0, p1), (v0, v1), (g0, g1) = pos.tolist(), vel.tolist(), goal.tolist()
        if (p0 - p0) + (p1 - p1) + (v0 - v0) + (v1 - v1) + (g0 - g0) + (g1 - g1) + (h - h) != 0.0:
            return None
        vdot = np.vdot  # unlike ndarray.dot, it does not warn when x.x overflows
        if k and not (
            vdot(nbr_pos_m, nbr_pos_m)
            + vdot(nbr_vel_m_s, nbr_vel_m_s)
            + vdot(nbr_heading_rad, nbr_heading_rad)
            < _INF
        ):
            return None
        return cls(pos, vel, h, goal, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad)

    @classmethod
    def _converted(
        cls, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad
    ):
        """Any input converted to float64 and checked, or the ValueError naming it."""
        pos_m = check_array("pos_m", pos_m, (2,), finite=False)
        vel_m_s = check_array("vel_m_s", vel_m_s, (2,), finite=False)
        if type(heading_rad) is float:  # the common case, without an array
            heading = heading_rad
        else:
            heading = float(check_array("heading_rad", heading_rad, (), finite=False))
        if not math.isfinite(heading):
            raise ValueError(f"heading_rad must be finite, got {heading!r}")
        goal_m = check_array("goal_m", goal_m, (2,), finite=False)
        nbr_pos_m = check_array("nbr_pos_m", nbr_pos_m, (-1, 2), finite=False)
        k = nbr_pos_m.shape[0]
        nbr_vel_m_s = check_array("nbr_vel_m_s", nbr_vel_m_s, (k, 2), finite=False)
        nbr_heading = check_array("nbr_heading_rad", nbr_heading_rad, (k,), finite=False)
        check_finite(
            pos_m=pos_m,
            vel_m_s=vel_m_s,
            goal_m=goal_m,
            nbr_pos_m=nbr_pos_m,
            nbr_vel_m_s=nbr_vel_m_s,
            nbr_heading_rad=nbr_heading,
        )
        return cls(pos_m, vel_m_s, heading, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading)

    def with_goal(self, goal_m) -> Observation:
        """The same observation flying to `goal_m` (a route's waypoint)."""
        return self._replace(goal_m=goal_m)

    def zoomed(self, factor: float) -> Observation:
        """The network's view at `factor` times the distances: the neighbours and the goal
        moved towards the own position (what a distance scale 1 / factor times as large
        sees; policy.runtime.told_scale)."""
        if factor == 1.0:
            return self
        p = self.pos_m
        return self._replace(
            goal_m=p + (self.goal_m - p) * factor, nbr_pos_m=p + (self.nbr_pos_m - p) * factor
        )

    def neighbours(self, keep) -> Observation:
        """Only the neighbours `keep` selects (a mask or indices)."""
        return Observation(
            self.pos_m,
            self.vel_m_s,
            self.heading_rad,
            self.goal_m,
            self.nbr_pos_m[keep],
            self.nbr_vel_m_s[keep],
            self.nbr_heading_rad[keep],
            self.sky.rows(keep),
        )


@dataclass(frozen=True)
class Observations:
    """N vehicles, each with its own view of K others padded with `nbr_valid` False (what
    each vehicle's link delivered: stale, lossy). Unchecked: built by simulations and the
    agents' views, which keep the shapes."""

    pos_m: np.ndarray
    """(N, 2)."""
    vel_m_s: np.ndarray
    """(N, 2)."""
    heading_rad: np.ndarray
    """(N,)."""
    goal_m: np.ndarray
    """(N, 2)."""
    nbr_pos_m: np.ndarray
    """(N, K, 2)."""
    nbr_vel_m_s: np.ndarray
    """(N, K, 2)."""
    nbr_heading_rad: np.ndarray
    """(N, K)."""
    nbr_valid: np.ndarray
    """(N, K) bool: this slot holds a neighbour."""
    pos_sigma_m: np.ndarray | None = None
    """(N,) own 1-sigma; None: exact."""
    nbr_pos_sigma_m: np.ndarray | None = None
    """(N, K) the neighbours' 1-sigma; None: exact."""
    nbr_cooperative: np.ndarray | None = None
    """(N, K) bool; None: all cooperate."""
    nbr_manned: np.ndarray | None = None
    """(N, K) bool, True for a manned aircraft (Sky.nbr_manned); None: none."""

    def nbr_sigma_max_m(self) -> np.ndarray:
        """(N,) each vehicle's largest cooperative neighbour 1-sigma (Sky.nbr_sigma_max_m;
        0: none, or exact)."""
        if self.nbr_pos_sigma_m is None or not self.nbr_valid.shape[1]:
            return np.zeros(self.pos_m.shape[0])
        keep = self.nbr_valid & _cooperative(
            self.nbr_valid.shape, self.nbr_cooperative, self.nbr_manned
        )
        return np.fmax.reduce(np.where(keep, self.nbr_pos_sigma_m, 0.0), axis=1, initial=0.0)

    def zoomed(self, factor: np.ndarray) -> Observations:
        """Observation.zoomed row by row, `factor` (N,)."""
        if not (factor != 1.0).any():
            return self
        p, f = self.pos_m, np.asarray(factor, float)[:, None]
        return replace(
            self,
            goal_m=p + (self.goal_m - p) * f,
            nbr_pos_m=p[:, None, :] + (self.nbr_pos_m - p[:, None, :]) * f[:, :, None],
        )

    def sky(self) -> dict:
        """The uncertainties as policy.safety's and policy.sparse's keyword arguments
        (nbr_manned only when given, as Sky.kwargs)."""
        out = {
            "pos_sigma_m": self.pos_sigma_m,
            "nbr_pos_sigma_m": self.nbr_pos_sigma_m,
            "nbr_cooperative": self.nbr_cooperative,
        }
        if self.nbr_manned is not None:
            out["nbr_manned"] = self.nbr_manned
        return out


@dataclass(frozen=True)
class Swarm:
    """N vehicles that each see every other active one (a simulation's true state, exact);
    inactive vehicles are invisible and get no command."""

    pos_m: np.ndarray
    """(N, 2)."""
    vel_m_s: np.ndarray
    """(N, 2)."""
    heading_rad: np.ndarray
    """(N,)."""
    goal_m: np.ndarray
    """(N, 2)."""
    active: np.ndarray
    """(N,) bool."""

    @classmethod
    def checked(cls, pos_m, vel_m_s, heading_rad, goal_m, active=None) -> Swarm:
        """The swarm of these rows (active None: all), or a ValueError naming the bad input."""
        pos_m = check_array("pos_m", pos_m, (-1, 2))
        n = pos_m.shape[0]
        vel_m_s = check_array("vel_m_s", vel_m_s, (n, 2))
        heading = check_array("heading_rad", heading_rad, (n,))
        goal_m = check_array("goal_m", goal_m, (n, 2))
        if active is None:
            active = np.ones(n, dtype=bool)
        active = np.asarray(active)
        if active.shape != (n,):
            raise ValueError(f"active must have shape ({n},), got {active.shape}")
        return cls(pos_m, vel_m_s, heading, goal_m, active.astype(bool))
