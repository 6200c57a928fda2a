"""Numpy runtime of the guidance policy (no torch): what the agents run.

    pol = GuidancePolicy.load()                 # shipped weights, flown as the agents fly them
    v_m_s = pol.command(pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad)

or, with the decision hold: `held = pol.preferred(...)` every `pol.decision_period_s`, and
`pol.filter(pos_m, vel_m_s, held, nbr_pos_m, nbr_vel_m_s)` every tick.

World frame: x north, y east, metres; heading 0 = north, clockwise positive.
The contract is docs/POLICY_SPEC.md; observations come from policy.features.
"""

from __future__ import annotations

import math
import threading
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kit.safe_load import npz_headers, parse_json
from policy import features, safety, sparse
from policy.features import ObsConfig
from policy.zone_lines import ZoneSet

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "policy.npz"
_F32 = np.dtype(np.float32)


FILTERED_BERTH_SHARE = 1.25 / 3.0
"""With the separation filter on, flight tells the policy this share of the separation (3 m ->
1.25 m), unless told otherwise: the network then keeps a narrower berth than the paper's and
leaves the separation itself to the filter. Chosen on seeds the repository had not used
(docs/policy.md, "The policy's berth"): conflicts 1.25 -> 1.09-1.11 extra time, large swarms
1.13 -> 1.05, 0 collisions and 100 % success on both links; told 1 m, a circle of 16 deadlocked
once on the degraded link."""


def told_separation_m(
    separation_m: float,
    safety_filter: bool,
    policy_separation_m: float | None = None,
    inflation_m: float = 0.0,
) -> float:
    """The separation flight tells the policy (its distance scale): `policy_separation_m` when
    given; else FILTERED_BERTH_SHARE x (separation_m + inflation_m) with the filter on, and
    separation_m + inflation_m without it (alone, the policy keeps the separation itself).
    The filter always keeps separation_m, plus its uncertainty inflation per pair
    (policy.safety.pair_radius_m); `inflation_m` tells the policy a typical one (0: none).
    One rule for the agents, fleet-sim, `covey eval` and the emulator's onboard C mode;
    firmware/covey_guidance.c covey_told_separation_m is its C twin (parity tested)."""
    if policy_separation_m is not None:
        return float(policy_separation_m)
    told = float(separation_m) + float(inflation_m)
    return told * (FILTERED_BERTH_SHARE if safety_filter else 1.0)


@dataclass(frozen=True)
class Network:
    """LSTM + tanh head weights, gates as (i, f, o, g), the sigmoid ones pre-scaled by 1/2.

    sigmoid(x) = (1 + tanh(x/2)) / 2, so one tanh per step serves all four gates.
    """

    w_ih: np.ndarray
    """(4H, X), rows of gates i, f, o scaled by 0.5."""
    w_hh_t: np.ndarray
    """(H, 4H) transposed recurrent weights, scaled like w_ih."""
    bias: np.ndarray
    """(4H,) b_ih + b_hh, scaled like w_ih."""
    head: tuple
    """((W, b), ...) of the tanh head, the output layer last."""
    hidden: int
    """LSTM hidden size H."""

    if TYPE_CHECKING:  # derived layouts that __post_init__ sets (not fields of the dataclass)
        _w_ib64: np.ndarray = field(init=False)
        _w_ib32: np.ndarray = field(init=False)
        _w_hh_half32: np.ndarray = field(init=False)
        _head_wb32: tuple[np.ndarray, ...] = field(init=False)
        _scratch: threading.local = field(init=False)

    @classmethod
    def from_arrays(cls, arrays: dict) -> Network:
        w_ih = np.asarray(arrays["lstm.weight_ih"], dtype=np.float64)
        w_hh = np.asarray(arrays["lstm.weight_hh"], dtype=np.float64)
        bias = np.asarray(arrays["lstm.bias"], dtype=np.float64)
        h = w_hh.shape[1]
        if w_ih.shape[0] != 4 * h or w_hh.shape != (4 * h, h) or bias.shape != (4 * h,):
            raise ValueError(f"inconsistent LSTM shapes {w_ih.shape}, {w_hh.shape}, {bias.shape}")
        # reorder torch's gates (i, f, g, o) to (i, f, o, g): the sigmoids become one slice
        perm = np.r_[0 : 2 * h, 3 * h : 4 * h, 2 * h : 3 * h]
        w_ih, w_hh, bias = w_ih[perm], w_hh[perm], bias[perm]
        scale = np.full(4 * h, 0.5)
        scale[3 * h :] = 1.0  # gate g is a real tanh
        head = []
        k = 0
        while f"head.{k}.weight" in arrays:
            head.append(
                (
                    np.asarray(arrays[f"head.{k}.weight"], dtype=np.float64),
                    np.asarray(arrays[f"head.{k}.bias"], dtype=np.float64),
                )
            )
            k += 1
        if not head:
            raise ValueError("weights file has no head.0.weight")
        return cls(
            w_ih * scale[:, None], (w_hh * scale[:, None]).T.copy(), bias * scale, tuple(head), h
        )

    def __post_init__(self) -> None:
        hs = self.hidden
        # fast path (lstm_last): gate columns reordered to (o, i, f, g), float32, the recurrent
        # rows halved because the loop carries h2 = 2h; the bias is the input projection's
        # last row (inputs get a constant 1); see lstm_last
        perm = np.r_[2 * hs : 3 * hs, 0 : 2 * hs, 3 * hs : 4 * hs]
        w_ib = np.vstack([self.w_ih.T[:, perm], self.bias[perm]])
        object.__setattr__(self, "_w_ib64", w_ib)
        object.__setattr__(self, "_w_ib32", w_ib.astype(np.float32))
        object.__setattr__(self, "_w_hh_half32", (0.5 * self.w_hh_t[:, perm]).astype(np.float32))
        # fast path (forward_one): each head layer as [W | b], float32, its input ending in 1
        object.__setattr__(
            self,
            "_head_wb32",
            tuple(np.hstack([w, b[:, None]]).astype(np.float32) for w, b in self.head),
        )
        object.__setattr__(self, "_scratch", threading.local())

    def rows_projection(self, dist_scale: float) -> np.ndarray:
        """The input projection (6, 4H), float32, of features.closest_last_rows' rows
        [d, 1, cos psi_ij, sin psi_ij, -cos psi_ji, sin psi_ji] (sincos encoding; the network
        sees d / dist_scale, so dist_scale carries the unit of d): the same XP rows as the
        sequence [d / dist_scale, sin psi_ij, cos psi_ij, sin psi_ji, cos psi_ji] with its
        constant 1 gives (lstm_last's layout)."""
        if self._w_ib64.shape[0] != 6:
            raise ValueError("rows_projection needs the sincos encoding (5 inputs)")
        w = self._w_ib64
        rows = [w[0] / dist_scale, w[5], w[2], w[1], -w[4], w[3]]
        return np.vstack(rows).astype(np.float32)

    def _lstm_scratch(self, n: int):
        """This thread's buffers for sequences up to n long (grown on demand): W = [W_hh / 2;
        XP rows], the input rows with their constant 1, the step buffers, the head's, and the
        table of features.closest_last_rows."""
        s = self._scratch
        have = getattr(s, "rows", None)
        if have is None or have < n:
            hs, x_n = self.hidden, self._w_ib32.shape[0]
            rows = max(n, 2 * (have or 0), 32)
            s.rows = rows
            s.w = np.zeros((hs + rows, 4 * hs), np.float32)
            s.w[:hs] = self._w_hh_half32
            s.x = np.ones((rows, x_n), np.float32)
            s.haug = np.zeros(hs + rows, np.float32)  # [h2, e_t]: e_t stays 0 between steps
            s.table = features.RowsTable(rows)
            buf = np.zeros(5 * hs, np.float32)  # [o, i, f, g, c]
            prod = np.zeros(2 * hs, np.float32)
            s.step = (
                buf[: 4 * hs],  # gates
                buf[: 3 * hs],  # the sigmoid gates
                buf[hs : 3 * hs],  # [i, f]
                buf[3 * hs :],  # [g, c]
                buf[:hs],  # o
                buf[4 * hs :],  # c
                prod,
                prod.reshape(2, hs),
                np.zeros(hs, np.float32),  # tanh(c)
                np.ones(3 * hs, np.float32),
                np.full(2, 0.5, np.float32),
            )
            # head inputs (each ending in 1, for the bias) and its output
            wbs = self._head_wb32
            z = [np.ones(wb.shape[1], np.float32) for wb in wbs]
            z.append(np.zeros(wbs[-1].shape[0], np.float32))
            last = len(wbs) - 1
            s.head = (
                z[0][:hs],
                z[0][hs:-1],
                tuple(
                    (wb, z[k], z[k + 1] if k == last else z[k + 1][:-1]) for k, wb in enumerate(wbs)
                ),
                z[-1],
                np.full(hs, 0.5, np.float32),
            )
        return s

    def rows_table(self, n: int) -> features.RowsTable:
        """This thread's scratch for features.closest_last_rows of n neighbours."""
        return self._lstm_scratch(n).table

    def lstm_last(self, seq: np.ndarray) -> np.ndarray:
        """Final hidden state of one sequence (L, X) -> (H,); zeros when L = 0 (`_lstm_h2`)."""
        h2 = self._lstm_h2(seq)
        return np.zeros(self.hidden) if h2 is None else 0.5 * h2.astype(np.float64)

    def forward_one(self, seq: np.ndarray, goal_feat) -> tuple[float, float]:
        """Unclipped head output of one sequence (L, X) and its goal features (G,): the fast
        path of head_forward(lstm_last(seq), goal_feat), equal within 1e-5. The head runs in
        float32 (like torch) on this thread's buffers, two numpy calls a layer:
        z' = tanh([W | b] [z; 1])."""
        return self._head_out(self._lstm_h2(seq), goal_feat)

    def forward_rows(self, rows: np.ndarray, proj: np.ndarray, goal_feat) -> tuple[float, float]:
        """`forward_one` of features.closest_last_rows' rows (L, 3) through their projection
        (`rows_projection`), goal features (G,) as a sequence of floats."""
        n = rows.shape[0]
        s = self._lstm_scratch(n)
        hs = self.hidden
        np.dot(rows.view(_F32), proj, s.w[hs : hs + n])
        return self._head_out(self._lstm_run(s, n), goal_feat)

    def _head_out(self, h2, goal_feat) -> tuple[float, float]:
        """The head on 2 x the final hidden state (None: zeros) and the goal features."""
        zh, zg, layers, out, half = self._scratch.head  # set up by the LSTM (any length)
        if h2 is None:
            zh[:] = 0.0
        else:
            np.multiply(h2, half, zh)
            np.tanh(zh, zh)
        zg[:] = goal_feat
        dot, tanh = np.dot, np.tanh
        for wb, z_in, z_out in layers:
            dot(wb, z_in, z_out)
            tanh(z_out, z_out)
        a0, a1 = out.tolist()
        return a0, a1

    def _lstm_h2(self, seq: np.ndarray) -> np.ndarray | None:
        """2 x the final hidden state of one sequence (L, X), float32, in this thread's scratch
        (valid until its next call); None when L = 0. The input projection of every neighbour
        in one matmul, (L, X + 1) @ (X + 1, 4H), then `_lstm_run`."""
        n = seq.shape[0]
        s = self._lstm_scratch(n)
        x = s.x[:n]
        x[:, :-1] = seq
        hs = self.hidden
        np.dot(x, self._w_ib32, s.w[hs : hs + n])
        return self._lstm_run(s, n)

    def _lstm_run(self, s, n: int) -> np.ndarray | None:
        """The recurrence over the n XP rows in s.w[H:H + n]: 2 x the final hidden state (in
        s.haug[:H]), or None when n = 0.

        The fast path of `lstm_last_reference` (equal within 1e-5, tests/test_policy_speed.py),
        float32 like torch. Per step it makes 7 numpy calls on one buffer B = [o, i, f, g, c]:
          B[:4H] = [h2, e_t] @ [W_hh / 2; XP]   (e_t one-hot: the input projection is a row;
                                                the first step, h = 0, is tanh(XP[0]) alone)
          B[:4H] = tanh(B[:4H]);  B[:3H] += 1   (2 sigma(x) = 1 + tanh(x / 2))
          P = B[H:3H] * B[3H:5H]                ([2 s_i g, 2 s_f c])
          c = [1/2, 1/2] @ [P[:H]; P[H:]];  h2 = (1 + tanh o) tanh(c) = 2 h
        Scalars come as arrays (a Python float operand costs a conversion per call).
        """
        if n == 0:
            return None
        hs = self.hidden
        gates, sig, pair, tail, o_gate, c, prod, prod2, th, ones, halves = s.step
        w = s.w[: hs + n]
        haug = s.haug[: hs + n]
        h2 = haug[:hs]
        dot, tanh, mul, add = np.dot, np.tanh, np.multiply, np.add
        c[:] = 0.0
        tanh(w[hs], gates)
        for t in range(hs, hs + n):
            if t > hs:
                haug[t] = 1.0
                dot(haug, w, gates)
                haug[t] = 0.0
                tanh(gates, gates)
            add(sig, ones, sig)
            mul(pair, tail, prod)
            dot(halves, prod2, c)
            tanh(c, th)
            mul(th, o_gate, h2)
        return h2

    def lstm_last_reference(self, seq: np.ndarray) -> np.ndarray:
        """Final hidden state of one sequence (L, X) -> (H,), float64, one step at a time."""
        hs = self.hidden
        h = np.zeros(hs)
        c = np.zeros(hs)
        if seq.shape[0] == 0:
            return h
        xp = seq @ self.w_ih.T + self.bias
        w = self.w_hh_t
        h3 = 3 * hs
        for t in range(seq.shape[0]):
            g = np.tanh(xp[t] + h @ w)
            s = g[:h3] * 0.5 + 0.5  # sigmoid(x) = (1 + tanh(x/2)) / 2
            c = s[hs : 2 * hs] * c + s[:hs] * g[h3:]
            h = s[2 * hs : h3] * np.tanh(c)
        return h

    def lstm_last_batch(self, seq: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Final hidden states (N, H) of zero-padded sequences (N, K, X) with lengths (N,).

        float32 (torch's precision), one matmul per step on [x_t, h] @ [W_ih; W_hh]^T.
        """
        n, k, x_n = seq.shape
        hs = self.hidden
        out = np.zeros((n, hs))
        if k == 0 or n == 0 or lengths.max() == 0:
            return out
        w = np.concatenate([self.w_ih.T, self.w_hh_t]).astype(np.float32)
        b = self.bias.astype(np.float32)
        # rows sorted by decreasing length: the rows still running at step t are a prefix
        order = np.argsort(-lengths, kind="stable")
        lens = lengths[order]
        kmax = int(lens[0])
        xs = seq[order, :kmax].astype(np.float32)
        xh = np.zeros((n, x_n + hs), np.float32)
        c = np.zeros((n, hs), np.float32)
        for t in range(kmax):
            r = int(np.searchsorted(-lens, -t, side="left"))  # rows with length > t
            xh[:r, :x_n] = xs[:r, t]
            g = xh[:r] @ w
            g += b
            np.tanh(g, out=g)
            g += 1.0  # i, f, o = (1 + g) / 2
            c[:r] = 0.5 * (g[:, hs : 2 * hs] * c[:r] + g[:, :hs] * (g[:, 3 * hs :] - 1.0))
            xh[:r, x_n:] = 0.5 * g[:, 2 * hs : 3 * hs] * np.tanh(c[:r])
        out[order] = xh[:, x_n:]
        return out

    def head_forward(self, h_last: np.ndarray, goal_feat: np.ndarray) -> np.ndarray:
        """Unclipped head output (..., 2)."""
        z = np.concatenate([np.tanh(h_last), goal_feat], axis=-1)
        for w, b in self.head:
            z = np.tanh(z @ w.T + b)
        return z


def _finite(**arrays) -> None:
    """One isfinite over all of them (the hot path); on a failure, the named ValueError."""
    if not np.isfinite(np.concatenate([a.ravel() for a in arrays.values()])).all():
        for name, a in arrays.items():
            if not np.isfinite(a).all():
                raise ValueError(f"{name} must be finite, got {a!r}")


_F64 = np.dtype(np.float64)
_INF = math.inf


def _clip_pair(a0: float, a1: float) -> tuple[float, float]:
    """(a0, a1) / |a| where |a| > 1 (features.clip_unit for one action)."""
    n = math.hypot(a0, a1)
    return (a0 / n, a1 / n) if n > 1.0 else (a0, a1)


def _check(name: str, x, shape: tuple, finite: bool = True) -> np.ndarray:
    """Array of the given shape (-1 = any length), finite (unless `finite` is False: the
    caller checks with `_finite`), or a ValueError saying which."""
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


def _sky(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, k: int) -> dict:
    """The filter's real-vehicle inputs, checked: pos_sigma_m a finite float >= 0,
    nbr_pos_sigma_m (k,) finite >= 0 or None, nbr_cooperative (k,) bool or None (k = -1: any
    length, checked later against the neighbours); a ValueError naming the bad one."""
    try:
        own = float(pos_sigma_m)
    except (TypeError, ValueError):
        raise ValueError(f"pos_sigma_m must be a number, got {pos_sigma_m!r}") from None
    if not (math.isfinite(own) and own >= 0.0):
        raise ValueError(f"pos_sigma_m must be finite and >= 0, got {own}")
    sig = None
    if nbr_pos_sigma_m is not None:
        sig = _check("nbr_pos_sigma_m", nbr_pos_sigma_m, (k,))
        if (sig < 0).any():
            raise ValueError(f"nbr_pos_sigma_m must be >= 0, got {sig!r}")
    coop = None
    if nbr_cooperative is not None:
        coop = np.asarray(nbr_cooperative)
        if coop.ndim != 1 or (k >= 0 and coop.shape != (k,)):
            raise ValueError(f"nbr_cooperative must have shape (K,) = ({k},), got {coop.shape}")
        if coop.dtype != bool and not np.isin(coop, (0, 1)).all():
            raise ValueError("nbr_cooperative must be booleans")
        coop = coop.astype(bool)
    return {"pos_sigma_m": own, "nbr_pos_sigma_m": sig, "nbr_cooperative": coop}


def _pair(x) -> list | tuple | None:
    """A finite-or-not (2,) float64 array, or a list / tuple of two Python floats, as two
    floats; None for anything else (the checked path then says what is wrong)."""
    if type(x) is np.ndarray:
        return x.tolist() if x.dtype is _F64 and x.shape == (2,) else None
    if type(x) in (list, tuple) and len(x) == 2 and type(x[0]) is float and type(x[1]) is float:
        return x
    return None


def _rows_f64(x, shape: tuple) -> bool:
    """x is a float64 array of exactly this shape."""
    return type(x) is np.ndarray and x.dtype is _F64 and x.shape == shape


MAX_WEIGHT_ARRAY_BYTES = 16 * 2**20
"""The largest array a weights file may hold (the shipped network's largest is 63 KiB)."""
MAX_CONFIG_CHARS = 65_536
"""The longest 'config' entry of a weights file (the shipped one is 181 characters)."""
LSTM_KEYS = {"lstm.weight_ih": 2, "lstm.weight_hh": 2, "lstm.bias": 1}
"""The LSTM's arrays and their dimensions; head.<k>.weight (2) and head.<k>.bias (1) follow."""


def load_weight_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of weights file `path` that the runtime uses, after the archive's member
    names and each array's header (dtype, dimensions, size) were checked against what it
    expects: a missing key, a wrong shape or a huge declared array is refused (ValueError,
    naming the key) before anything is loaded."""
    heads = npz_headers(path)
    where = f"weights file {path}"

    def need(name: str, ndim: int) -> None:
        h = heads.get(name)
        if h is None:
            raise ValueError(f"{where} has no {name!r} array (not covey weights?)")
        if name == "config":
            if h.dtype.kind != "U" or h.shape != () or h.dtype.itemsize > 4 * MAX_CONFIG_CHARS:
                raise ValueError(
                    f"{where}: 'config' must be one JSON text, got {h.dtype} {h.shape}"
                )
            return
        if h.dtype.kind != "f" or len(h.shape) != ndim or 0 in h.shape:
            raise ValueError(
                f"{where}: {name!r} must be a non-empty {ndim}-D float array, "
                f"got {h.dtype} of shape {h.shape}"
            )
        if h.nbytes > MAX_WEIGHT_ARRAY_BYTES:
            raise ValueError(
                f"{where}: {name!r} declares {h.shape} ({h.nbytes} bytes), over the "
                f"{MAX_WEIGHT_ARRAY_BYTES} byte limit"
            )

    names = ["config", *LSTM_KEYS]
    for name in names:
        need(name, LSTM_KEYS.get(name, 0))
    k = 0
    while f"head.{k}.weight" in heads or k == 0:
        need(f"head.{k}.weight", 2)
        need(f"head.{k}.bias", 1)
        names += [f"head.{k}.weight", f"head.{k}.bias"]
        k += 1
    try:
        with np.load(path, allow_pickle=False) as z:
            return {name: z[name] for name in names}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # a torn member
        raise ValueError(f"{where}: cannot read it ({' '.join(str(exc).split())})") from None


class GuidancePolicy:
    """The trained guidance policy with world-unit scaling and an optional safety filter."""

    def __init__(
        self,
        net: Network,
        obs_cfg: ObsConfig,
        config: dict,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        safety_filter: bool = True,
        max_neighbours: int | None = None,
        safety_cfg: safety.SafetyConfig | None = None,
        policy_separation_m: float | None = None,
        sparse_rule: sparse.SparseConfig | bool | None = True,
        keep_out_m=None,
        fence_m=None,
    ):
        """The defaults fly as the agents do (agent.guidance.GuidanceConfig).

        `keep_out_m` [(K, 2) polygon vertices, local north/east metres] and `fence_m` (K, 2):
        see `set_zones`; None: no zones (today's behaviour).

        `policy_separation_m`: the separation the network is told, i.e. its distance scale (3
        policy units = this many metres). None: as flight tells it, `told_separation_m` (1.25 m
        per 3 m of separation with the filter on, the whole separation without it). Smaller
        than separation_m makes the policy keep a narrower berth while the filter still keeps
        separation_m (docs/policy.md, "The policy's berth"). The decision period stays
        separation_m's.

        `sparse_rule`: in sparse traffic, command the straight line at the goal instead of the
        policy's velocity (policy.sparse), for flight that filters every command, which then
        resolves the encounter. True: SparseConfig() with the filter on, off without it; a
        SparseConfig: these thresholds, also without this policy's filter (for a caller that
        filters every tick itself, as the agents do); False or None: the policy always."""
        if not (np.isfinite(separation_m) and separation_m > 0):
            raise ValueError(f"separation_m must be finite and > 0, got {separation_m}")
        if not (np.isfinite(cruise_speed_m_s) and cruise_speed_m_s > 0):
            raise ValueError(f"cruise_speed_m_s must be finite and > 0, got {cruise_speed_m_s}")
        if max_neighbours is not None and max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0 or None, got {max_neighbours}")
        self.net = net
        self.obs_cfg = obs_cfg
        self.config = config
        policy_separation_m = told_separation_m(separation_m, safety_filter, policy_separation_m)
        if not (np.isfinite(policy_separation_m) and policy_separation_m > 0):
            raise ValueError(
                f"policy_separation_m must be finite and > 0, got {policy_separation_m}"
            )
        self.dist_scale_m = policy_separation_m / 3.0
        """World metres per policy unit of distance (what the network sees)."""
        self.separation_m = float(separation_m)
        """The separation the filter keeps."""
        self.cruise_speed_m_s = cruise_speed_m_s
        self.max_neighbours = max_neighbours
        self.safety_filter = safety_filter
        if sparse_rule is None or isinstance(sparse_rule, (bool, np.bool_)):
            sparse_rule = sparse.SparseConfig() if sparse_rule and safety_filter else None
        elif not isinstance(sparse_rule, sparse.SparseConfig):
            raise TypeError(
                f"sparse_rule must be a SparseConfig, True, False or None, got {sparse_rule!r}"
            )
        self.sparse_rule: sparse.SparseConfig | None = sparse_rule
        """The rule's thresholds, None when it is off."""
        base = safety_cfg or safety.SafetyConfig()
        self.safety_cfg = replace(base, radius_m=separation_m, max_speed_m_s=cruise_speed_m_s)
        # the fast path of `command` / `action` (features.closest_last_rows): the projection of
        # rows in metres and in policy units, and the sense range in each; None = not this config
        self._rows_proj_m = self._rows_proj = None
        if (obs_cfg.encoding, obs_cfg.order) == ("sincos", "closest_last"):
            self._rows_proj = net.rows_projection(obs_cfg.dist_scale)
            self._rows_proj_m = net.rows_projection(obs_cfg.dist_scale * self.dist_scale_m)
        self._sense_range_m = obs_cfg.sense_range * self.dist_scale_m
        self.zones: ZoneSet | None = None
        """Keep-out edges the filter keeps clear of (policy.zone_lines), None: none."""
        self.router = None
        """The route planner around them (policy.routes.Router), None: none."""
        if keep_out_m is not None or fence_m is not None:
            self.set_zones(keep_out_m or (), fence_m)

    def set_zones(self, keep_out_m, fence_m=None) -> None:
        """Keep out of these polygons [(K, 2) north/east metres] (and inside the fence):
        `command` and `preferred` fly towards the route planner's next waypoint instead of the
        goal (policy.routes: around the zones inflated by the filter's zone radius plus a
        margin), and the filter (when on) keeps ZONE_CLEARANCE_SHARE x the padded separation
        from every zone edge as a hard constraint (policy.zone_lines). Empty: no zones. A bad
        polygon is a ValueError naming it."""
        from policy.routes import zones_for  # shapely and scipy: only with zones

        self.zones, self.router = zones_for(self.safety_cfg, keep_out_m, fence_m)

    def waypoint(self, pos_m, goal_m):
        """Where to fly now for `goal_m` (2,): the route's next waypoint with zones, else
        the goal. Inputs that are not two finite numbers come back as they are (the checked
        path names them)."""
        if self.router is None:
            return goal_m
        try:
            return self.router.next_waypoint(pos_m, goal_m)
        except (TypeError, ValueError):
            return goal_m

    def waypoints(self, pos_m, goal_m) -> np.ndarray:
        """`waypoint` of N rows (N, 2)."""
        if self.router is None:
            return goal_m
        return self.router.next_waypoints(pos_m, goal_m)

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        safety_filter: bool = True,
        max_neighbours: int | None = None,
        safety_cfg: safety.SafetyConfig | None = None,
        policy_separation_m: float | None = None,
        sparse_rule: sparse.SparseConfig | bool | None = True,
        keep_out_m=None,
        fence_m=None,
    ) -> GuidancePolicy:
        """Loads a weights file (docs/POLICY_SPEC.md); None = the shipped weights. The other
        arguments are the constructor's: the defaults fly as the agents do."""
        path = Path(path) if path is not None else DEFAULT_WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(f"no policy weights at {path}")
        arrays = load_weight_arrays(path)
        config = parse_json(str(arrays["config"]), f"{path} 'config'")
        if not isinstance(config, dict):
            raise ValueError(f"{path}: 'config' is not a JSON object")
        if config.get("encoder", "lstm") != "lstm":
            raise ValueError(
                f"{path}: the runtime only runs encoder 'lstm', not {config['encoder']!r}"
            )
        try:
            obs_cfg = ObsConfig.from_dict(config)
            net = Network.from_arrays(arrays)
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise ValueError(f"{path}: not usable weights ({' '.join(str(exc).split())})") from None
        if net.w_ih.shape[1] != obs_cfg.input_size:
            raise ValueError(
                f"{path}: LSTM input {net.w_ih.shape[1]} does not fit encoding {obs_cfg.encoding}"
            )
        return cls(
            net,
            obs_cfg,
            config,
            separation_m,
            cruise_speed_m_s,
            safety_filter,
            max_neighbours,
            safety_cfg,
            policy_separation_m,
            sparse_rule,
            keep_out_m,
            fence_m,
        )

    @property
    def decision_period_s(self) -> float:
        """World time of one training step (1 s in policy units): call `preferred` at this
        period and hold it in between, running `filter` on it at the control rate (as the
        agents do); or call `command` at the control rate."""
        return float(self.config.get("dt_s", 1.0)) * self.separation_m / 3.0 / self.cruise_speed_m_s

    def filter(
        self,
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
    ):
        """The safety filter alone (world units): pref_vel_m_s changed as little as possible.
        Uncertainties and cooperative flags as `command` takes them."""
        pos_m = _check("pos_m", pos_m, (2,))
        nbr_pos_m = _check("nbr_pos_m", nbr_pos_m, (-1, 2))
        sky = _sky(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_pos_m.shape[0])
        return safety.filter_velocity(
            pos_m,
            _check("vel_m_s", vel_m_s, (2,)),
            _check("pref_vel_m_s", pref_vel_m_s, (2,)),
            nbr_pos_m,
            _check("nbr_vel_m_s", nbr_vel_m_s, (nbr_pos_m.shape[0], 2)),
            self.safety_cfg,
            **sky,
            zones=self.zones,
        )

    # --- policy units -------------------------------------------------------------

    def action(self, pos, heading_rad, goal, nbr_pos, nbr_heading_rad) -> np.ndarray:
        """Raw network action (a_fwd, a_right), clipped to |a| <= 1; inputs in policy units.

        The fast path of `action_reference`, equal within 1e-5 (tests/test_policy_speed.py):
        `_action_rows` where it applies, else features.observe_fast and Network.forward_one
        (the LSTM in float32 either way)."""
        a = None
        if self._rows_proj is not None:
            pos = np.asarray(pos, dtype=np.float64)
            goal = np.asarray(goal, dtype=np.float64)
            h = float(heading_rad)
            p0, p1, g0, g1 = float(pos[0]), float(pos[1]), float(goal[0]), float(goal[1])
            a = self._action_rows(
                pos,
                p0,
                p1,
                h,
                g0,
                g1,
                np.asarray(nbr_pos, dtype=np.float64).reshape(-1, 2),
                np.asarray(nbr_heading_rad, dtype=np.float64),
                self._rows_proj,
                self.obs_cfg.sense_range,
            )
        if a is None:
            seq, goal_feat, _ = features.observe_fast(
                pos, heading_rad, goal, nbr_pos, nbr_heading_rad, self.obs_cfg, self.max_neighbours
            )
            a = _clip_pair(*self.net.forward_one(seq, goal_feat))
        return np.array(a)

    def _action_rows(
        self, pos, p0, p1, heading, g0, g1, nbr_pos, nbr_heading, proj, sense_range
    ) -> tuple[float, float] | None:
        """The clipped action through features.closest_last_rows and Network.forward_rows
        (sincos / closest_last, every neighbour kept), in any length unit: proj and
        sense_range in that unit; pos (2,) also as floats p0, p1, the goal as g0, g1. None
        where that does not apply (more than max_neighbours, a neighbour on top, a
        non-finite distance): the caller takes the general path."""
        k = nbr_pos.shape[0]
        if self.max_neighbours is not None and k > self.max_neighbours:
            return None
        net = self.net
        got = features.closest_last_rows(
            nbr_pos - pos, heading, nbr_heading, sense_range, net.rows_table(k)
        )
        if got is None:
            return None
        psi_d = math.atan2(g1 - p1, g0 - p0) - heading
        return _clip_pair(*net.forward_rows(got[0], proj, (math.sin(psi_d), math.cos(psi_d))))

    def action_reference(self, pos, heading_rad, goal, nbr_pos, nbr_heading_rad) -> np.ndarray:
        """`action` the plain way: features.observe, float64 LSTM one step at a time."""
        seq, goal_feat, _ = features.observe(
            pos, heading_rad, goal, nbr_pos, nbr_heading_rad, self.obs_cfg, self.max_neighbours
        )
        h = self.net.lstm_last_reference(seq)
        return features.clip_unit(self.net.head_forward(h, goal_feat))

    def action_batch(self, pos, heading_rad, goal, active, rows=None):
        """Raw actions (N, 2) and neighbour indices (N, K) of all vehicles; policy units.

        `rows` (indices): run the network for these vehicles only and return their actions
        (len(rows), 2); the neighbour indices are still every vehicle's (a safety filter needs them).
        """
        seq, lengths, goal_feat, nbr = features.observe_batch(
            pos, heading_rad, goal, active, self.obs_cfg, self.max_neighbours
        )
        if rows is not None:
            seq, lengths, goal_feat = seq[rows], lengths[rows], goal_feat[rows]
        h = self.net.lstm_last_batch(seq, lengths)
        return features.clip_unit(self.net.head_forward(h, goal_feat)), nbr

    # --- world units ----------------------------------------------------------------

    def command(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
    ):
        """Velocity command (2,) in m/s (north, east) for one vehicle.

        Real vehicles: `pos_sigma_m` is the own position estimate's 1-sigma (metres, per axis;
        PX4's eph), `nbr_pos_sigma_m` (K,) the neighbours' as they reported them, and
        `nbr_cooperative` (K,) bool False for a neighbour that does not avoid (traffic): the
        filter keeps each pair apart by separation_m (1 + margin) + sigma_k sqrt(si^2 + sj^2)
        and takes the whole correction against traffic (policy.safety.pair_radius_m). The
        defaults (0, None, None) fly as before.

        Inputs that are already float64 arrays of the right shapes (a 2-vector may also be a
        list of two floats, the heading a float), with the shipped observation, take
        `_command_fast`; anything else, and every bad input, `_command_checked`, which
        names what is wrong. Both give the same velocity within 1e-5.

        Called every tick, this is all a caller needs. For the decision hold (as the agents
        fly), hold `preferred` instead and `filter` it every tick: a held `command` keeps the
        filter's answer to the moment it decided, on top of the filter's answer to now."""
        return self._command(
            pos_m,
            vel_m_s,
            heading_rad,
            goal_m,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_heading_rad,
            True,
            pos_sigma_m,
            nbr_pos_sigma_m,
            nbr_cooperative,
        )

    def preferred(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
    ):
        """The velocity (2,) to hold for one decision period, as the agents do: the policy's,
        or the sparse rule's straight line, not yet filtered. Every tick, fly
        `filter(pos_m, vel_m_s, held, nbr_pos_m, nbr_vel_m_s)`; at the decision that is
        `command`. Same inputs and checks as `command`."""
        return self._command(
            pos_m,
            vel_m_s,
            heading_rad,
            goal_m,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_heading_rad,
            False,
            pos_sigma_m,
            nbr_pos_sigma_m,
            nbr_cooperative,
        )

    def _command(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        filtered,
        pos_sigma_m=0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
    ) -> np.ndarray:
        if self.router is not None:
            goal_m = self.waypoint(pos_m, goal_m)
        sky = None
        if pos_sigma_m or nbr_pos_sigma_m is not None or nbr_cooperative is not None:
            k = np.shape(nbr_pos_m)[0] if np.ndim(nbr_pos_m) == 2 else -1
            sky = _sky(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, k)
        v = self._command_fast(
            pos_m,
            vel_m_s,
            heading_rad,
            goal_m,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_heading_rad,
            filtered,
            sky,
        )
        if v is None:
            v = self._command_checked(
                pos_m,
                vel_m_s,
                heading_rad,
                goal_m,
                nbr_pos_m,
                nbr_vel_m_s,
                nbr_heading_rad,
                filtered,
                sky,
            )
        return v

    def _command_fast(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        filtered: bool = True,
        sky: dict | None = None,
    ) -> np.ndarray | None:
        """`command` in metres without scaling the inputs (the projection takes metres), or
        None when the inputs are not the common case or not all finite.

        Finite: (x - x) is 0 for a finite float and NaN otherwise; x.x over a neighbour array
        is finite exactly when its entries are (or it overflows: then the checked path);
        positions through the distances (features.closest_last_rows)."""
        if self._rows_proj_m is None or type(nbr_pos_m) is not np.ndarray or nbr_pos_m.ndim != 2:
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
        (p0, p1), (v0, v1), (g0, g1), h = pos, vel, goal, float(heading_rad)
        if (p0 - p0) + (p1 - p1) + (v0 - v0) + (v1 - v1) + (g0 - g0) + (g1 - g1) + (h - h) != 0.0:
            return None
        vdot = np.vdot  # unlike ndarray.dot, it does not warn when x.x overflows
        if k and not vdot(nbr_vel_m_s, nbr_vel_m_s) + vdot(nbr_heading_rad, nbr_heading_rad) < _INF:
            return None
        a = self._action_rows(
            np.asarray(pos_m),
            p0,
            p1,
            h,
            g0,
            g1,
            nbr_pos_m,
            nbr_heading_rad,
            self._rows_proj_m,
            self._sense_range_m,
        )
        if a is None:
            return None
        return self._velocity(a, h, pos_m, vel_m_s, goal_m, nbr_pos_m, nbr_vel_m_s, filtered, sky)

    def _velocity(
        self,
        a,
        heading,
        pos_m,
        vel_m_s,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        filtered: bool = True,
        sky: dict | None = None,
    ) -> np.ndarray:
        """Body (fwd, right) action a -> (north, east) velocity times the cruise speed, then
        the sparse rule (when on), then the filter (when on, `filtered`, and there are
        neighbours)."""
        c, sn, u = math.cos(heading), math.sin(heading), self.cruise_speed_m_s
        a0, a1 = a
        v = np.array(((a0 * c - a1 * sn) * u, (a0 * sn + a1 * c) * u))
        if self.sparse_rule is not None:
            v, _ = sparse.choose_one(
                pos_m,
                vel_m_s,
                goal_m,
                v,
                nbr_pos_m,
                nbr_vel_m_s,
                self.safety_cfg,
                self.sparse_rule,
                self.decision_period_s,
                **(sky or {}),
            )
        if filtered and self.safety_filter and (nbr_pos_m.shape[0] or self.zones is not None):
            v = safety.filter_one(
                pos_m,
                vel_m_s,
                v,
                nbr_pos_m,
                nbr_vel_m_s,
                self.safety_cfg,
                **(sky or {}),
                zones=self.zones,
            )
        return v

    def _command_checked(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        filtered: bool = True,
        sky: dict | None = None,
    ) -> np.ndarray:
        """`command` for any input: checked (a ValueError naming the input), then scaled to
        policy units and through `action`."""
        pos_m = _check("pos_m", pos_m, (2,), finite=False)
        vel_m_s = _check("vel_m_s", vel_m_s, (2,), finite=False)
        if type(heading_rad) is float:  # the common case, without an array
            heading = heading_rad
        else:
            heading = float(_check("heading_rad", heading_rad, (), finite=False))
        if not math.isfinite(heading):
            raise ValueError(f"heading_rad must be finite, got {heading!r}")
        goal_m = _check("goal_m", goal_m, (2,), finite=False)
        nbr_pos_m = _check("nbr_pos_m", nbr_pos_m, (-1, 2), finite=False)
        k = nbr_pos_m.shape[0]
        nbr_vel_m_s = _check("nbr_vel_m_s", nbr_vel_m_s, (k, 2), finite=False)
        nbr_heading = _check("nbr_heading_rad", nbr_heading_rad, (k,), finite=False)
        if sky is not None and sky["nbr_pos_sigma_m"] is not None:
            sky = {
                **sky,
                "nbr_pos_sigma_m": _check("nbr_pos_sigma_m", sky["nbr_pos_sigma_m"], (k,)),
            }
        if sky is not None and sky["nbr_cooperative"] is not None:
            coop = np.asarray(sky["nbr_cooperative"])
            if coop.shape != (k,):
                raise ValueError(f"nbr_cooperative must have shape ({k},), got {coop.shape}")
            sky = {**sky, "nbr_cooperative": coop.astype(bool)}
        _finite(
            pos_m=pos_m,
            vel_m_s=vel_m_s,
            goal_m=goal_m,
            nbr_pos_m=nbr_pos_m,
            nbr_vel_m_s=nbr_vel_m_s,
            nbr_heading_rad=nbr_heading,
        )
        s = self.dist_scale_m
        a = self.action(pos_m / s, heading, goal_m / s, nbr_pos_m / s, nbr_heading)
        return self._velocity(
            (float(a[0]), float(a[1])),
            heading,
            pos_m,
            vel_m_s,
            goal_m,
            nbr_pos_m,
            nbr_vel_m_s,
            filtered,
            sky,
        )

    def _sparse(self, pos_m, vel_m_s, goal_m, v, nbr_pos_m, nbr_vel_m_s, nbr_valid, **sky):
        """policy.sparse.choose_padded with this policy's filter and decision period (`sky`:
        its uncertainties and cooperative flags)."""
        return sparse.choose_padded(
            pos_m,
            vel_m_s,
            goal_m,
            v,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_valid,
            self.safety_cfg,
            self.sparse_rule,
            self.decision_period_s,
            **sky,
        )

    def command_batch(self, pos_m, vel_m_s, heading_rad, goal_m, active=None):
        """Velocity commands (N, 2) in m/s; each active vehicle sees all other active ones.

        Inactive vehicles get (0, 0) and are invisible to the others.
        """
        pos_m = _check("pos_m", pos_m, (-1, 2))
        n = pos_m.shape[0]
        vel_m_s = _check("vel_m_s", vel_m_s, (n, 2))
        heading = _check("heading_rad", heading_rad, (n,))
        goal_m = _check("goal_m", goal_m, (n, 2))
        if active is None:
            active = np.ones(n, dtype=bool)
        active = np.asarray(active)
        if active.shape != (n,):
            raise ValueError(f"active must have shape ({n},), got {active.shape}")
        active = active.astype(bool)
        goal_m = self.waypoints(pos_m, goal_m)
        s = self.dist_scale_m
        a, nbr = self.action_batch(pos_m / s, heading, goal_m / s, active)
        v = features.action_to_velocity(a, heading) * self.cruise_speed_m_s
        if self.sparse_rule is not None:  # encounters reach past the network's sense range
            others = active[None, :] & ~np.eye(n, dtype=bool)
            every_pos, every_vel = (np.broadcast_to(x, (n, n, 2)) for x in (pos_m, vel_m_s))
            v, _ = self._sparse(pos_m, vel_m_s, goal_m, v, every_pos, every_vel, others)
        if self.safety_filter:
            v = safety.filter_batch(pos_m, vel_m_s, v, nbr, self.safety_cfg, zones=self.zones)
        v[~active] = 0.0
        return v

    def command_views(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        nbr_valid,
        pos_sigma_m=None,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
    ):
        """Velocity commands (N, 2) in m/s when each vehicle has its own view of the others.

        nbr_* are (N, K, ...) padded with nbr_valid (N, K) False: what each vehicle's link
        delivered (stale, lossy); pos_sigma_m (N,), nbr_pos_sigma_m and nbr_cooperative (N, K)
        as `command` takes them (None: exact, all cooperative). Unchecked fast path for
        simulations.
        """
        sky = {
            "pos_sigma_m": pos_sigma_m,
            "nbr_pos_sigma_m": nbr_pos_sigma_m,
            "nbr_cooperative": nbr_cooperative,
        }
        goal_m = self.waypoints(pos_m, goal_m)
        s = self.dist_scale_m
        seq, lengths, goal_feat, _ = features.observe_padded(
            pos_m / s,
            heading_rad,
            goal_m / s,
            nbr_pos_m / s,
            nbr_heading_rad,
            nbr_valid,
            self.obs_cfg,
            self.max_neighbours,
        )
        a = features.clip_unit(
            self.net.head_forward(self.net.lstm_last_batch(seq, lengths), goal_feat)
        )
        v = features.action_to_velocity(a, heading_rad) * self.cruise_speed_m_s
        if self.sparse_rule is not None:
            v, _ = self._sparse(pos_m, vel_m_s, goal_m, v, nbr_pos_m, nbr_vel_m_s, nbr_valid, **sky)
        if self.safety_filter:
            v = safety.filter_padded(
                pos_m,
                vel_m_s,
                v,
                nbr_pos_m,
                nbr_vel_m_s,
                nbr_valid,
                self.safety_cfg,
                **sky,
                zones=self.zones,
            )
        return v
