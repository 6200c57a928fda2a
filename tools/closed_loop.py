"""Closed-loop replay: feed one vehicle's recorded traffic through a policy and compare commands.

For every recorded state of vehicle V in which its agent ran guidance (goto, return or hold),
rebuild what the agent saw — its own position, velocity, heading and goal, and its neighbour
table — run `agent.guidance.Guidance` with the given policy, and compare the horizontal
commanded velocity with the recorded reference.

Reference and inputs, best first:
- a guidance trace (comms.schema.GuidanceTrace on `msg/<id>/trace`; an agent with
  `--trace-guidance` publishes one per tick that publishes a state): the exact command, the
  heading the policy saw and which neighbour samples (id, seq, age) it used. Replaying the same
  policy then gives a difference at float32 rounding level (the published state's). Recordings
  made before the trace had its own message carry it as event text (`parse_trace`).
- without traces: the recorded velocity of V (the vehicle's response, not the command) and the
  neighbour table rebuilt from the recorder's receive times. Approximate; the report says so.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from agent.guidance import Guidance, GuidanceConfig
from agent.neighbours import NeighbourConfig, NeighbourSnapshot
from comms import keys
from comms.schema import DecodeError, Event, GuidanceTrace, Mode, StateFlag, VehicleState
from recording.record import Recording, read_recording

GUIDED_MODES = (Mode.GOTO, Mode.RETURNING, Mode.HOLDING)
LEGACY_TRACE_PREFIX = "trace "


def parse_trace(text: str, vehicle_id: int = 0, stamp_ns: int = 0) -> GuidanceTrace | None:
    """The trace in an event's text, as agents published it before GuidanceTrace existed, or
    None if the text is not a (valid) one. The format: `trace <seq> <heading> <vn>,<ve>,<vd>
    D|H <id>:<seq>:<age_us>;...`, cut to the event's 120 bytes (a final `+` marks a cut
    neighbour list); D: the policy decided in this tick, H: held (no flag: decided).
    `vehicle_id` and `stamp_ns` are the event's."""
    if not text.startswith(LEGACY_TRACE_PREFIX):
        return None
    parts = text[len(LEGACY_TRACE_PREFIX) :].split(" ")
    try:
        seq, heading, vel = (
            int(parts[0]),
            float(parts[1]),
            tuple(float(x) for x in parts[2].split(",")),
        )
        rest = parts[3:]
        decided = True
        if rest and rest[0] in ("D", "H"):
            decided, rest = rest[0] == "D", rest[1:]
        body = rest[0] if rest else ""
        complete = not body.endswith("+")
        nbrs = tuple(
            (int(i), int(s), int(a) / 1e6)
            for i, s, a in (item.split(":") for item in body.rstrip("+").split(";") if item)
        )
    except (ValueError, IndexError):
        return None
    if len(vel) != 3 or not all(map(math.isfinite, (heading, *vel))):
        return None
    return GuidanceTrace(vehicle_id, seq, stamp_ns, heading, vel, nbrs, complete, decided)


# -- replay ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class ClosedLoopConfig:
    """Which vehicle of which recording to replay through which policy."""

    path: str
    """The MCAP recording."""
    vehicle_id: int
    """The vehicle whose traffic is replayed."""
    policy_path: str | None = None
    """Policy weights (.npz); None = the shipped weights."""
    separation_m: float = 3.0
    """As the agent flew (covey agent --separation-m)."""
    cruise_speed_m_s: float = 1.0
    """As the agent flew (covey agent --cruise-speed-m-s)."""
    safety_filter: bool = True
    """As the agent flew (off with covey agent --no-safety-filter)."""
    start_s: float = 0.0
    """Skip the first start_s seconds of the recording."""
    end_s: float | None = None
    """Stop at this many seconds into the recording."""
    neighbours: NeighbourConfig = NeighbourConfig()
    """The agent's neighbour-table settings (staleness, vertical band)."""


@dataclass(frozen=True)
class _Sample:
    t_ns: int
    state: VehicleState


def _index(rec: Recording, vid: int):
    own: list[_Sample] = []
    others: dict[int, list[_Sample]] = {}
    traces: dict[int, GuidanceTrace] = {}
    for m in rec.messages:
        parsed = keys.parse_vehicle_key(m.topic)
        if parsed is None:
            continue
        try:
            if parsed[2] == "state":
                s = VehicleState.decode(m.data)
                (own if s.vehicle_id == vid else others.setdefault(s.vehicle_id, [])).append(
                    _Sample(m.log_time_ns, s)
                )
            elif parsed[2] == "trace" and parsed[1] == vid:
                tr = GuidanceTrace.decode(m.data)
                if tr.vehicle_id == vid:
                    traces[tr.state_seq] = tr
            elif parsed[2] == "event" and parsed[1] == vid:
                ev = Event.decode(m.data)
                from_event = parse_trace(ev.text, ev.vehicle_id, ev.stamp_ns)
                if from_event is not None:
                    traces[from_event.state_seq] = from_event
        except DecodeError:
            continue
    return own, others, traces


def _snapshot(rows: list[tuple[VehicleState, float]], stale_s: float) -> NeighbourSnapshot:
    """The agent's NeighbourSnapshot: positions dead-reckoned by age (p + v age)."""
    k = len(rows)
    pos = [np.asarray(s.pos_ned_m, float) + np.asarray(s.vel_ned_m_s, float) * a for s, a in rows]
    return NeighbourSnapshot(
        pos_ned_m=np.array(pos, dtype=float).reshape(k, 3),
        vel_ned_m_s=np.array([s.vel_ned_m_s for s, _ in rows], dtype=float).reshape(k, 3),
        heading_rad=np.array([s.heading_rad for s, _ in rows], dtype=float).reshape(k),
        ids=tuple(s.vehicle_id for s, _ in rows),
        age_s=np.array([a for _, a in rows], dtype=float).reshape(k),
        stale_ids=tuple(s.vehicle_id for s, a in rows if a > stale_s),
    )


def _traced_rows(tr: GuidanceTrace, by_seq: dict[tuple[int, int], list[_Sample]], t_ns: int):
    rows = []
    for vid, seq, age_s in tr.neighbours:
        # seq wraps only after 13 years at 10 Hz, but an agent restart reuses seqs: take the
        # latest sample with that seq the recorder had by then.
        cands = [x for x in by_seq.get((vid, seq), ()) if x.t_ns <= t_ns + 1_000_000_000]
        if not cands:
            return None  # the recorder missed the sample the agent used
        rows.append((cands[-1].state, age_s))
    return rows


def _rebuilt_rows(
    others: dict[int, tuple[list[int], list[_Sample]]],
    t_ns: int,
    own: VehicleState,
    cfg: NeighbourConfig,
):
    rows = []
    for times, samples in others.values():
        i = bisect.bisect_right(times, t_ns) - 1
        if i < 0:
            continue
        s, age_s = samples[i].state, (t_ns - samples[i].t_ns) / 1e9
        if age_s > cfg.drop_s or (s.mode in (Mode.LANDED, Mode.KILLED) and not s.armed):
            continue
        if abs(s.pos_ned_m[2] + s.vel_ned_m_s[2] * age_s - own.pos_ned_m[2]) > cfg.vertical_band_m:
            continue
        rows.append((s, age_s))
    return rows


def run_closed_loop(
    cfg: ClosedLoopConfig, recording: Recording | None = None, guidance: Guidance | None = None
) -> dict:
    """Replay and compare; returns the report (JSON-ready)."""
    rec = recording if recording is not None else read_recording(cfg.path)
    guidance = guidance or Guidance(
        GuidanceConfig(
            separation_m=cfg.separation_m,
            cruise_speed_m_s=cfg.cruise_speed_m_s,
            safety_filter=cfg.safety_filter,
            policy_path=cfg.policy_path,
        )
    )
    own, others, traces = _index(rec, cfg.vehicle_id)
    by_seq: dict[tuple[int, int], list[_Sample]] = {}
    for samples in others.values():
        for x in samples:
            by_seq.setdefault((x.state.vehicle_id, x.state.seq), []).append(x)
    timed = {vid: ([x.t_ns for x in samples], samples) for vid, samples in others.items()}
    if not own:
        raise ValueError(f"{cfg.path}: no states of vehicle {cfg.vehicle_id} in the recording")
    t0 = rec.messages[0].log_time_ns
    lo, hi = (
        t0 + round(cfg.start_s * 1e9),
        None if cfg.end_s is None else t0 + round(cfg.end_s * 1e9),
    )
    use_traces = bool(traces)
    rows_out, skipped = [], 0
    prev_heading = None
    chain_ok = False  # traced: the held decision was replayed too (else held ticks are skipped)
    for sample in own:
        s, t_ns = sample.state, sample.t_ns
        heading_in = prev_heading
        prev_heading = s.heading_rad
        if t_ns < lo or (hi is not None and t_ns >= hi):
            continue
        if not (s.armed and s.mode in GUIDED_MODES and s.flags & StateFlag.HAS_GOAL):
            guidance.reset()
            chain_ok = False
            continue
        decide = None  # recorded velocities: guidance decides on its own clock
        if use_traces:
            tr = traces.get(s.seq)
            nbr_rows = _traced_rows(tr, by_seq, t_ns) if tr is not None and tr.complete else None
            if nbr_rows is None or not (tr.decided or chain_ok or s.mode is Mode.HOLDING):
                skipped += 1
                chain_ok = False
                continue
            chain_ok, decide = True, tr.decided
            heading_in, ref = tr.heading_rad, np.array(tr.cmd_vel_ned_m_s[:2])
        else:
            nbr_rows = _rebuilt_rows(timed, t_ns, s, cfg.neighbours)
            v = s.vel_ned_m_s
            if math.hypot(v[0], v[1]) > 0.2 * cfg.cruise_speed_m_s or heading_in is None:
                heading_in = (
                    math.atan2(v[1], v[0]) if math.hypot(v[0], v[1]) > 1e-9 else s.heading_rad
                )
            ref = np.array(v[:2])
        snap = _snapshot(nbr_rows, cfg.neighbours.stale_s)
        pos, vel, goal = (
            np.asarray(x, dtype=float) for x in (s.pos_ned_m, s.vel_ned_m_s, s.goal_ned_m)
        )
        if s.mode is Mode.HOLDING:
            out = guidance.hold(pos, vel, heading_in, goal, snap).vel_ned_m_s[:2]
        else:
            out = guidance.goto(pos, vel, heading_in, goal, snap, t_ns / 1e9, decide).vel_ned_m_s[
                :2
            ]
        rows_out.append(
            ((t_ns - t0) / 1e9, s.seq, s.pos_ned_m, out, ref, float(np.linalg.norm(out - ref)))
        )
    return _report(cfg, rows_out, skipped, "trace" if use_traces else "recorded_velocity")


def _report(cfg: ClosedLoopConfig, rows: list, skipped: int, reference: str) -> dict:
    diffs = np.array([r[5] for r in rows])
    worst = rows[int(np.argmax(diffs))] if rows else None
    return {
        "vehicle_id": cfg.vehicle_id,
        "policy": cfg.policy_path or "shipped",
        "reference": reference,
        "exact": reference == "trace",
        "ticks": len(rows),
        "skipped_ticks": skipped,
        "max_diff_m_s": float(diffs.max()) if rows else 0.0,
        "p95_diff_m_s": float(np.percentile(diffs, 95)) if rows else 0.0,
        "mean_diff_m_s": float(diffs.mean()) if rows else 0.0,
        "worst": None
        if worst is None
        else {
            "t_s": worst[0],
            "seq": worst[1],
            "pos_ned_m": list(worst[2]),
            "commanded_m_s": worst[3].tolist(),
            "reference_m_s": worst[4].tolist(),
        },
        "largest": [
            {"t_s": r[0], "seq": r[1], "pos_ned_m": list(r[2]), "diff_m_s": r[5]}
            for r in sorted(rows, key=lambda r: -r[5])[:10]
        ],
    }


def format_report(rep: dict) -> str:
    ref = (
        "traced commands (exact)" if rep["exact"] else "recorded velocity (approximate: no traces)"
    )
    lines = [
        f"closed-loop replay of vehicle {rep['vehicle_id']} with policy {rep['policy']}",
        f"reference   {ref}",
        f"ticks       {rep['ticks']} compared, {rep['skipped_ticks']} skipped",
        f"difference  max {rep['max_diff_m_s']:.3g} m/s, p95 {rep['p95_diff_m_s']:.3g} m/s, "
        f"mean {rep['mean_diff_m_s']:.3g} m/s",
        "",
        f"{'t s':>8} {'seq':>6} {'north m':>9} {'east m':>9} {'diff m/s':>10}",
    ]
    for r in rep["largest"]:
        n, e = r["pos_ned_m"][0], r["pos_ned_m"][1]
        lines.append(f"{r['t_s']:>8.2f} {r['seq']:>6} {n:>9.2f} {e:>9.2f} {r['diff_m_s']:>10.3g}")
    return "\n".join(lines)
