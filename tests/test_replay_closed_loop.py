"""Closed-loop replay: the same policy reproduces the traced commands; another one does not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.guidance import Guidance, GuidanceConfig
from agent.neighbours import NeighbourTable
from comms import keys
from comms.schema import Event, GuidanceTrace, Mode, Severity, StateFlag, VehicleState
from recording.record import McapSink, read_recording
from tools.closed_loop import ClosedLoopConfig, format_report, parse_trace, run_closed_loop

FLEET = "cl"
TICK_S = 0.1


def trace_text(
    state_seq: int,
    heading_rad: float,
    cmd_vel_ned_m_s,
    nbr_ids,
    nbr_seqs,
    nbr_ages_s,
    max_bytes: int = 120,
    decided: bool = True,
) -> str:
    """A trace as agents published it in event text before GuidanceTrace existed (what old
    recordings hold): `trace <seq> <heading> <vn>,<ve>,<vd> D|H <id>:<seq>:<age_us>;...` cut
    to max_bytes (a final `+` marks a cut neighbour list); D: decided in this tick, H: held."""
    v = ",".join(f"{float(x):.9g}" for x in cmd_vel_ned_m_s)
    text = f"trace {state_seq} {float(heading_rad):.9g} {v} {'D' if decided else 'H'} "
    items = [
        f"{i}:{s}:{round(a * 1e6)}" for i, s, a in zip(nbr_ids, nbr_seqs, nbr_ages_s, strict=True)
    ]
    body = ";".join(items)
    if len((text + body).encode()) <= max_bytes:
        return text + body
    while items and len((text + ";".join(items) + "+").encode()) > max_bytes:
        items.pop()
    return text + ";".join(items) + "+"


def _fly(path, n_ticks=120, traces=True, cruise=1.0, legacy=False):
    """Three vehicles crossing, each run by agent.guidance as the agent does it, with neighbour
    states that arrive late (ages vary) and are dead-reckoned; writes states and traces to MCAP
    (GuidanceTrace on the trace key, or with `legacy` as event text, as older agents did)."""
    starts = {1: (0.0, 0.0), 2: (10.0, 10.0), 3: (10.0, -10.0)}
    goals = {1: (20.0, 0.0), 2: (0.0, -8.0), 3: (0.0, 8.0)}
    pos = {v: np.array([*p, -5.0]) for v, p in starts.items()}
    vel = {v: np.zeros(3) for v in pos}
    heading = {v: math.atan2(goals[v][1] - starts[v][1], goals[v][0] - starts[v][0]) for v in pos}
    tables = {v: NeighbourTable(v) for v in pos}
    # One Guidance per vehicle, as one agent each: the policy decides once a second and holds.
    guidance = {v: Guidance(GuidanceConfig(cruise_speed_m_s=cruise)) for v in pos}
    rng = np.random.default_rng(3)
    t_ns = 1_700_000_000_000_000_000
    with open(path, "wb") as f:
        sink = McapSink(f, FLEET, 4096, 0.05)
        inflight = []
        for k in range(1, n_ticks + 1):
            t_ns += round(TICK_S * 1e9)
            now_s = t_ns / 1e9
            for arrive_ns, dst, st in [x for x in inflight if x[0] <= t_ns]:
                tables[dst].update(st, arrive_ns / 1e9)
            inflight = [x for x in inflight if x[0] > t_ns]
            for v in sorted(pos):
                goal = np.array([*goals[v], -5.0])
                snap = tables[v].snapshot(now_s, pos[v])
                h_in = heading[v]
                out = guidance[v].goto(pos[v], vel[v], h_in, goal, snap, now_s)
                state = VehicleState(
                    v,
                    k,
                    t_ns,
                    tuple(pos[v]),
                    tuple(vel[v]),
                    float(math.remainder(out.heading_rad, 2 * math.pi)),
                    mode=Mode.GOTO,
                    armed=True,
                    flags=StateFlag.HAS_GOAL,
                    goal_ned_m=tuple(goal),
                )
                sink.put(keys.state(FLEET, v), state.encode(), t_ns + v)
                if traces:
                    seqs = [tables[v].latest()[i].seq for i in snap.ids]
                    if legacy:
                        text = trace_text(
                            k,
                            h_in,
                            out.vel_ned_m_s,
                            snap.ids,
                            seqs,
                            snap.age_s,
                            decided=out.decided,
                        )
                        ev = Event(v, t_ns, text, Severity.DEBUG)
                        sink.put(keys.event(FLEET, v), ev.encode(), t_ns + v + 1)
                    else:
                        tr = GuidanceTrace.build(
                            v,
                            k,
                            t_ns,
                            h_in,
                            out.vel_ned_m_s,
                            snap.ids,
                            seqs,
                            snap.age_s,
                            out.decided,
                        )
                        sink.put(keys.trace(FLEET, v), tr.encode(), t_ns + v + 1)
                for dst in pos:
                    if dst != v and rng.random() > 0.2:  # 20 % loss, 0-250 ms late
                        inflight.append(
                            (
                                t_ns + int(rng.uniform(0, 0.25e9)),
                                dst,
                                VehicleState.decode(state.encode()),
                            )
                        )
                heading[v] = out.heading_rad
                vel[v] = out.vel_ned_m_s
            for v in pos:
                pos[v] = pos[v] + vel[v] * TICK_S
        sink.close()


def test_trace_text_round_trips_and_fits():
    text = trace_text(42, -1.25, (0.5, -0.25, 0.0), (2, 3), (41, 40), (0.0123456, 0.2))
    tr = parse_trace(text)
    assert (
        tr.state_seq == 42 and tr.heading_rad == -1.25 and tr.cmd_vel_ned_m_s == (0.5, -0.25, 0.0)
    )
    assert tr.neighbours == ((2, 41, 0.012346), (3, 40, 0.2)) and tr.complete
    many = trace_text(7, 0.1, (0.1, 0.2, 0.3), range(1, 40), range(1000, 1039), [0.1] * 39)
    assert len(many.encode()) <= 120 and many.endswith("+")
    assert not parse_trace(many).complete
    assert parse_trace("hello") is None and parse_trace("trace x y z") is None


def test_same_policy_reports_zero_difference(tmp_path):
    path = tmp_path / "cl.mcap"
    _fly(path)
    rep = run_closed_loop(ClosedLoopConfig(str(path), vehicle_id=1))
    assert rep["reference"] == "trace" and rep["exact"]
    assert rep["ticks"] == 120 and rep["skipped_ticks"] == 0
    assert rep["max_diff_m_s"] < 1e-4  # float32 rounding of the published state only
    assert "closed-loop replay of vehicle 1" in format_report(rep)


def test_event_text_traces_of_older_recordings_replay_exactly(tmp_path):
    path = tmp_path / "cl.mcap"
    _fly(path, legacy=True)
    assert not any(m.topic.endswith("/trace") for m in read_recording(path).messages)
    rep = run_closed_loop(ClosedLoopConfig(str(path), vehicle_id=1))
    assert rep["reference"] == "trace" and rep["exact"]
    assert rep["ticks"] == 120 and rep["skipped_ticks"] == 0
    assert rep["max_diff_m_s"] < 1e-4


def test_traces_have_their_own_key_and_count_in_the_summary(tmp_path):
    from recording.record import summarise

    path = tmp_path / "cl.mcap"
    _fly(path, n_ticks=5)
    rec = read_recording(path)
    traces = [GuidanceTrace.decode(m.data) for m in rec.messages if m.topic.endswith("/trace")]
    assert len(traces) == 15 and {t.vehicle_id for t in traces} == {1, 2, 3}
    assert summarise(rec)["counts"] == {"states": 15, "traces": 15}


def test_different_policy_settings_show_a_difference(tmp_path):
    path = tmp_path / "cl.mcap"
    _fly(path)
    rep = run_closed_loop(ClosedLoopConfig(str(path), vehicle_id=2, cruise_speed_m_s=0.5))
    assert rep["max_diff_m_s"] > 0.2
    assert rep["worst"]["t_s"] >= 0 and len(rep["worst"]["pos_ned_m"]) == 3


def test_without_traces_compares_with_recorded_velocity(tmp_path):
    path = tmp_path / "cl.mcap"
    _fly(path, traces=False)
    rep = run_closed_loop(ClosedLoopConfig(str(path), vehicle_id=3))
    assert rep["reference"] == "recorded_velocity" and not rep["exact"]
    assert rep["ticks"] == 120
    # The recorded velocity is the previous tick's command here: close, not equal.
    assert 0.0 < rep["p95_diff_m_s"] < 0.5


def test_unknown_vehicle_is_a_clear_error(tmp_path):
    path = tmp_path / "cl.mcap"
    _fly(path, n_ticks=5)
    with pytest.raises(ValueError, match="no states of vehicle 9"):
        run_closed_loop(ClosedLoopConfig(str(path), vehicle_id=9))
    assert len(read_recording(path).messages) == 30


def test_cli_prints_a_table_and_writes_json(tmp_path, capsys):
    import json

    from policy.runtime import DEFAULT_WEIGHTS
    from tools.replay_cli import replay_cli

    path, out = tmp_path / "cl.mcap", tmp_path / "report.json"
    _fly(path, n_ticks=30)
    code = replay_cli(
        [str(path), "--policy", str(DEFAULT_WEIGHTS), "--vehicle", "2", "--json-out", str(out)]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "closed-loop replay of vehicle 2" in printed and "diff m/s" in printed
    rep = json.loads(out.read_text())
    assert rep["ticks"] == 30 and rep["max_diff_m_s"] < 1e-4


def test_cli_rejects_half_a_closed_loop_request(tmp_path):
    from tools.replay_cli import replay_cli

    path = tmp_path / "cl.mcap"
    _fly(path, n_ticks=3)
    with pytest.raises(SystemExit) as exc:
        replay_cli([str(path), "--vehicle", "2"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        replay_cli([str(tmp_path / "missing.mcap")])
    with pytest.raises(SystemExit):
        replay_cli([str(path), "--speed", "0"])
