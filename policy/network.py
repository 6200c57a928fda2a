"""The guidance network in numpy (no torch): an LSTM over the neighbours and a tanh head.

    net = Network.from_arrays(load_weight_arrays(path))   # a weights file (docs/POLICY_SPEC.md)
    a = net.forward_one(seq, goal_feat)                   # fast path, float32 like torch
    h = net.lstm_last_reference(seq)                      # the plain float64 reference

The weights are checked before they are loaded (load_weight_arrays); policy.actor runs the
network on observations, policy.runtime flies it.
"""

from __future__ import annotations

import threading
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kit.safe_load import npz_headers
from policy import features

_F32 = np.dtype(np.float32)


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
