"""Numpy runtime of the guidance policy (no torch): what the agents run.

    pol = GuidancePolicy.load()                 # shipped weights
    v_m_s = pol.command(pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad)

World frame: x north, y east, metres; heading 0 = north, clockwise positive.
The contract is docs/POLICY_SPEC.md; observations come from policy.features.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from policy import features, safety
from policy.features import ObsConfig

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "policy.npz"


FILTERED_BERTH_SHARE = 1.25 / 3.0
"""With the separation filter on, flight tells the policy this share of the separation (3 m ->
1.25 m), unless told otherwise: the network then keeps a narrower berth than the paper's and
leaves the separation itself to the filter. Chosen on seeds the repository had not used
(docs/policy.md, "The policy's berth"): conflicts 1.25 -> 1.09-1.11 extra time, large swarms
1.13 -> 1.05, 0 collisions and 100 % success on both links; told 1 m, a circle of 16 deadlocked
once on the degraded link."""


def told_separation_m(
    separation_m: float, safety_filter: bool, policy_separation_m: float | None = None
) -> float:
    """The separation flight tells the policy (its distance scale): `policy_separation_m` when
    given; else FILTERED_BERTH_SHARE x separation_m with the filter on, and separation_m without
    it (alone, the policy keeps the separation itself). The filter always keeps separation_m.
    One rule for the agents, fleet-sim, `covey eval` and the emulator's onboard C mode;
    firmware/covey_guidance.c covey_told_separation_m is its C twin (parity tested)."""
    if policy_separation_m is not None:
        return float(policy_separation_m)
    return float(separation_m) * (FILTERED_BERTH_SHARE if safety_filter else 1.0)


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
        w_ib = np.vstack([self.w_ih.T[:, perm], self.bias[perm]]).astype(np.float32)
        object.__setattr__(self, "_w_ib32", w_ib)
        object.__setattr__(self, "_w_hh_half32", (0.5 * self.w_hh_t[:, perm]).astype(np.float32))
        # fast path (forward_one): each head layer as [W | b], its input ending in a constant 1
        object.__setattr__(
            self, "_head_wb", tuple(np.hstack([w, b[:, None]]) for w, b in self.head)
        )
        object.__setattr__(self, "_scratch", threading.local())

    def _lstm_scratch(self, n: int) -> tuple:
        """This thread's buffers for sequences up to n long (grown on demand): W = [W_hh / 2;
        XP rows], the input rows with their constant 1, and the step buffers."""
        s = self._scratch
        have = getattr(s, "rows", None)
        if have is None or have < n:
            hs, x_n = self.hidden, self._w_ib32.shape[0]
            rows = max(n, 2 * (have or 0), 32)
            s.rows = rows
            s.w = np.zeros((hs + rows, 4 * hs), np.float32)
            s.w[:hs] = self._w_hh_half32
            s.x = np.ones((rows, x_n), np.float32)
            s.haug = np.zeros(hs + rows, np.float32)
            s.buf = np.zeros(5 * hs, np.float32)
            s.prod = np.zeros(2 * hs, np.float32)
            s.th = np.zeros(hs, np.float32)
            s.ones = np.ones(3 * hs, np.float32)
            s.halves = np.full(2, 0.5, np.float32)
            # head inputs (each ending in 1, for the bias) and its output
            s.z = [np.ones(wb.shape[1]) for wb in self._head_wb] + [np.zeros(self.head[-1][1].size)]
        return s.w, s.x, s.haug, s.buf, s.prod, s.th, s.ones, s.halves

    def lstm_last(self, seq: np.ndarray) -> np.ndarray:
        """Final hidden state of one sequence (L, X) -> (H,); zeros when L = 0 (`_lstm_h2`)."""
        h2 = self._lstm_h2(seq)
        return np.zeros(self.hidden) if h2 is None else 0.5 * h2.astype(np.float64)

    def forward_one(self, seq: np.ndarray, goal_feat: np.ndarray) -> tuple[float, float]:
        """Unclipped head output of one sequence (L, X) and its goal features (G,): the fast
        path of head_forward(lstm_last(seq), goal_feat), equal within 1e-5. The head runs in
        float64 on this thread's buffers, two numpy calls a layer: z' = tanh([W | b] [z; 1])."""
        h2 = self._lstm_h2(seq)
        z = self._scratch.z  # set up by _lstm_h2 (any length)
        hs = self.hidden
        z0 = z[0]
        if h2 is None:
            z0[:hs] = 0.0
        else:
            np.multiply(h2, 0.5, z0[:hs])
            np.tanh(z0[:hs], z0[:hs])
        z0[hs:-1] = goal_feat
        last = len(self._head_wb) - 1
        for k, wb in enumerate(self._head_wb):
            out = z[k + 1] if k == last else z[k + 1][:-1]
            np.dot(wb, z[k], out)
            np.tanh(out, out)
        a = z[-1]
        return float(a[0]), float(a[1])

    def _lstm_h2(self, seq: np.ndarray) -> np.ndarray | None:
        """2 x the final hidden state of one sequence (L, X), float32, in this thread's scratch
        (valid until its next call); None when L = 0.

        The fast path of `lstm_last_reference` (equal within 1e-5, tests/test_policy_speed.py),
        float32 like torch. Per step it makes 7 numpy calls on one buffer B = [o, i, f, g, c]:
          B[:4H] = [h2, e_t] @ [W_hh / 2; XP]   (XP = [X, 1] [W_ih^T; b] for all steps at once,
                                                e_t one-hot: the input projection is a row)
          B[:4H] = tanh(B[:4H]);  B[:3H] += 1   (2 sigma(x) = 1 + tanh(x / 2))
          P = B[H:3H] * B[3H:5H]                ([2 s_i g, 2 s_f c])
          c = [1/2, 1/2] @ [P[:H]; P[H:]];  h2 = (1 + tanh o) tanh(c) = 2 h
        Scalars come as arrays (a Python float operand costs a conversion per call).
        """
        hs = self.hidden
        n = seq.shape[0]
        w_all, x, haug_all, buf, prod, th, ones, halves = self._lstm_scratch(n)
        # the input projection of every neighbour in one matmul: (L, X + 1) @ (X + 1, 4H)
        x[:n, :-1] = seq
        w = w_all[: hs + n]
        np.dot(x[:n], self._w_ib32, w[hs:])
        haug = haug_all[: hs + n]  # [h2, e_t]
        haug[:] = 0.0
        h2 = haug[:hs]
        buf[4 * hs :] = 0.0  # c
        gates, sig, pair, c = buf[: 4 * hs], buf[: 3 * hs], buf[hs : 3 * hs], buf[4 * hs :]
        tail, o_gate, prod2 = buf[3 * hs :], buf[:hs], prod.reshape(2, hs)
        dot, tanh, mul, add = np.dot, np.tanh, np.multiply, np.add
        for t in range(hs, hs + n):
            haug[t] = 1.0
            if t > hs:
                haug[t - 1] = 0.0
            dot(haug, w, gates)
            tanh(gates, gates)
            add(sig, ones, sig)
            mul(pair, tail, prod)
            dot(halves, prod2, c)
            tanh(c, th)
            mul(th, o_gate, h2)
        return h2 if n else None

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
    ):
        """`policy_separation_m`: the separation the network is told, i.e. its distance scale
        (3 policy units = this many metres); None = separation_m. Smaller than separation_m
        makes the policy keep a narrower berth while the filter still keeps separation_m
        (docs/policy.md, "A narrower berth"). The decision period stays separation_m's."""
        if not (np.isfinite(separation_m) and separation_m > 0):
            raise ValueError(f"separation_m must be finite and > 0, got {separation_m}")
        if not (np.isfinite(cruise_speed_m_s) and cruise_speed_m_s > 0):
            raise ValueError(f"cruise_speed_m_s must be finite and > 0, got {cruise_speed_m_s}")
        if max_neighbours is not None and max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0 or None, got {max_neighbours}")
        self.net = net
        self.obs_cfg = obs_cfg
        self.config = config
        if policy_separation_m is None:
            policy_separation_m = separation_m
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
        base = safety_cfg or safety.SafetyConfig()
        self.safety_cfg = replace(base, radius_m=separation_m, max_speed_m_s=cruise_speed_m_s)

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
    ) -> GuidancePolicy:
        """Loads a weights file (docs/POLICY_SPEC.md); None = the shipped weights."""
        path = Path(path) if path is not None else DEFAULT_WEIGHTS
        if not path.is_file():
            raise FileNotFoundError(f"no policy weights at {path}")
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        if "config" not in arrays:
            raise ValueError(f"{path} has no 'config' entry")
        config = json.loads(str(arrays["config"]))
        if config.get("encoder", "lstm") != "lstm":
            raise ValueError(
                f"{path}: the runtime only runs encoder 'lstm', not {config['encoder']!r}"
            )
        obs_cfg = ObsConfig.from_dict(config)
        net = Network.from_arrays(arrays)
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
        )

    @property
    def decision_period_s(self) -> float:
        """World time of one training step (1 s in policy units): call `command` at this
        period and hold the velocity in between; run `filter` at the control rate."""
        return float(self.config.get("dt_s", 1.0)) * self.separation_m / 3.0 / self.cruise_speed_m_s

    def filter(self, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s):
        """The safety filter alone (world units): pref_vel_m_s changed as little as possible."""
        pos_m = _check("pos_m", pos_m, (2,))
        nbr_pos_m = _check("nbr_pos_m", nbr_pos_m, (-1, 2))
        return safety.filter_velocity(
            pos_m,
            _check("vel_m_s", vel_m_s, (2,)),
            _check("pref_vel_m_s", pref_vel_m_s, (2,)),
            nbr_pos_m,
            _check("nbr_vel_m_s", nbr_vel_m_s, (nbr_pos_m.shape[0], 2)),
            self.safety_cfg,
        )

    # --- policy units -------------------------------------------------------------

    def action(self, pos, heading_rad, goal, nbr_pos, nbr_heading_rad) -> np.ndarray:
        """Raw network action (a_fwd, a_right), clipped to |a| <= 1; inputs in policy units.

        The fast path (features.observe_fast, Network.forward_one: the LSTM in float32) of
        `action_reference`, equal within 1e-5 (tests/test_policy_speed.py)."""
        seq, goal_feat, _ = features.observe_fast(
            pos, heading_rad, goal, nbr_pos, nbr_heading_rad, self.obs_cfg, self.max_neighbours
        )
        a0, a1 = self.net.forward_one(seq, goal_feat)
        n = math.hypot(a0, a1)
        return np.array([a0 / n, a1 / n]) if n > 1.0 else np.array([a0, a1])

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

    def command(self, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad):
        """Velocity command (2,) in m/s (north, east) for one vehicle."""
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
        # body (fwd, right) -> (north, east), times the cruise speed
        c, sn, u = math.cos(heading), math.sin(heading), self.cruise_speed_m_s
        a0, a1 = float(a[0]), float(a[1])
        v = np.array([(a0 * c - a1 * sn) * u, (a0 * sn + a1 * c) * u])
        if self.safety_filter and k:
            v = safety.filter_one(pos_m, vel_m_s, v, nbr_pos_m, nbr_vel_m_s, self.safety_cfg)
        return v

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
        s = self.dist_scale_m
        a, nbr = self.action_batch(pos_m / s, heading, goal_m / s, active)
        v = features.action_to_velocity(a, heading) * self.cruise_speed_m_s
        if self.safety_filter:
            v = safety.filter_batch(pos_m, vel_m_s, v, nbr, self.safety_cfg)
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
    ):
        """Velocity commands (N, 2) in m/s when each vehicle has its own view of the others.

        nbr_* are (N, K, ...) padded with nbr_valid (N, K) False: what each vehicle's link
        delivered (stale, lossy). Unchecked fast path for simulations.
        """
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
        if self.safety_filter:
            v = safety.filter_padded(
                pos_m, vel_m_s, v, nbr_pos_m, nbr_vel_m_s, nbr_valid, self.safety_cfg
            )
        return v
