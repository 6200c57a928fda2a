"""HTML for the fleet table, the ack matrix, the command log and the mode legend (pure: data
in, str out)."""

from __future__ import annotations

import html
import math
import time
from collections.abc import Callable, Iterable

from comms.commands import OutcomeStatus
from comms.geo import GeoOrigin
from comms.schema import ActionOutcome, EventMessage
from groundstation.command_log import LoggedCommand, PlanChange, Status, progress_all
from groundstation.dispatch import Dispatched
from groundstation.fleet import FleetSnapshot, VehicleView
from groundstation.palette import ALERT_RGB, MODE_RGB, TRAFFIC_RGB, css, mode_rgb

_TABLE = (
    '<table style="width:100%;border-collapse:collapse;font-size:0.78em;'
    'font-variant-numeric:tabular-nums">'
)
_TH = '<th style="text-align:{a};padding:1px 3px;border-bottom:1px solid #999;white-space:nowrap">{t}</th>'
_TD = '<td style="text-align:{a};padding:1px 3px;{s}">{t}</td>'


def _td(text: str, align: str = "right", style: str = "") -> str:
    return _TD.format(a=align, s=style, t=text)


def _mode_badge(v: VehicleView) -> str:
    if not v.alive and v.state is not None:
        return f'<b style="color:{css(ALERT_RGB)}">LOST</b>'
    if v.mode is None:
        return "—"
    return f'<span style="color:{css(mode_rgb(v.mode))};font-weight:bold">{v.mode.name}</span>'


def _link(v: VehicleView) -> str:
    if v.state is None:
        return _td("no state", style=f"color:{css(ALERT_RGB)}") * 3
    age_style = f"color:{css(ALERT_RGB)};font-weight:bold" if v.stale else ""
    loss_style = f"color:{css(ALERT_RGB)}" if v.loss_pct >= 10.0 else ""
    age = f"{v.age_s:.1f}" if math.isfinite(v.age_s) else "—"
    return (
        _td(f"{v.rate_hz:.1f}")
        + _td(age, style=age_style)
        + _td(f"{v.loss_pct:.0f}", style=loss_style)
    )


_HEAD_TITLES = {
    "N m": "metres north of the fleet origin",
    "E m": "metres east of the fleet origin",
    "alt m": "altitude above the fleet origin, metres, up",
    "lat": "latitude, degrees (WGS-84)",
    "lon": "longitude, degrees (WGS-84)",
}


def fleet_table(
    snap: FleetSnapshot,
    max_rows: int = 60,
    refused_states: int = 0,
    origin: GeoOrigin | None = None,
) -> str:
    """One row per vehicle: id, mode, armed, N/E/alt (above the origin), lat/lon (with an
    `origin`), speed, battery, Hz, age, loss. `refused_states`: states the mesh refused (keyed
    mode), shown as a counter."""
    heads = [
        ("id", "right"),
        ("mode", "left"),
        ("arm", "center"),
        ("N m", "right"),
        ("E m", "right"),
        ("alt m", "right"),
        *((("lat", "right"), ("lon", "right")) if origin is not None else ()),
        ("m/s", "right"),
        ("bat %", "right"),
        ("Hz", "right"),
        ("age s", "right"),
        ("loss %", "right"),
    ]
    rows = [
        "<tr>"
        + "".join(
            _TH.format(a=a, t=f'<span title="{_HEAD_TITLES[t]}">{t}</span>')
            if t in _HEAD_TITLES
            else _TH.format(a=a, t=t)
            for t, a in heads
        )
        + "</tr>"
    ]
    for v in snap.vehicles[:max_rows]:
        clock = v.clock_offset_s
        alert = v.too_close or (not v.alive and v.state) or v.unverified or clock is not None
        row_style = "background:#fde2e2" if alert else ""
        mode = _mode_badge(v)
        if clock is not None:  # its own signed report: the cause, not the last state it could send
            mode = (
                f"<b data-clock='1' style='color:{css(ALERT_RGB)}' title='vehicle clock minus "
                "station clock: past 5 s its states and commands are refused as stale; set "
                f"its time (NTP or GPS)'>CLOCK {clock:+.1f} s</b>"
            )
        elif v.unverified:  # keyed mode: states claiming this vehicle failed verification lately
            mode += (
                f" <b data-unverified='1' style='color:{css(ALERT_RGB)}'>UNVERIFIED "
                f"({html.escape(v.refused_cause)})</b>"
            )
        if v.state is not None and v.state.mission_items:  # mission item k of n
            k, n = v.state.mission_item, v.state.mission_items
            text = "done" if k > n else f"item {k}/{n}" if k else f"loaded, {n} items"
            mode += f" <span data-mission='{k}/{n}' style='font-size:0.85em'>{text}</span>"
        cells = [_td(f"<b>{v.vehicle_id}</b>"), _td(mode, "left")]
        s = v.state
        if s is None:
            cells += [_td("—", "center")] + [_td("")] * (5 if origin is None else 7)
        else:
            bat_style = f"color:{css(ALERT_RGB)};font-weight:bold" if s.battery_pct < 20 else ""
            n_m, e_m = s.pos_ned_m[0], s.pos_ned_m[1]
            cells += [
                _td("●" if s.armed else "○", "center"),
                _td(f"{n_m:.1f}"),
                _td(f"{e_m:.1f}"),
                _td(f"{v.alt_m:.1f}"),
            ]
            if origin is not None:
                lat, lon, _ = origin.to_global(n_m, e_m, 0.0)
                cells += [_td(f"{lat:.6f}"), _td(f"{lon:.6f}")]
            cells += [
                _td(f"{v.speed_m_s:.1f}"),
                _td(f"{s.battery_pct:.0f}", style=bat_style),
            ]
        cells.append(_link(v))
        rows.append(
            f'<tr data-vehicle="{v.vehicle_id}" style="{row_style}">' + "".join(cells) + "</tr>"
        )
    more = len(snap.vehicles) - max_rows
    foot = f"<div style='font-size:0.75em'>… and {more} more</div>" if more > 0 else ""
    alive = sum(v.alive for v in snap.vehicles)
    summary = f"<div style='font-size:0.8em;margin-bottom:2px'><b>{alive}</b> of {len(snap.vehicles)} vehicles present"
    if refused_states:
        summary += f" · {refused_states} states from unknown vehicles refused"
    if snap.unverified_present:
        summary += (
            f" · {snap.unverified_present:,} presence tokens of unverified vehicles (not listed)"
        )
    if snap.close_pairs:
        pairs = ", ".join(f"{a}–{b} ({d:.1f} m)" for a, b, d in snap.close_pairs[:5])
        summary += f" · <b style='color:{css(ALERT_RGB)}'>TOO CLOSE: {html.escape(pairs)}</b>"
    summary += "</div>"
    return summary + _TABLE + "".join(rows) + "</table>" + foot


_STATUS_STYLE = {
    OutcomeStatus.ACCEPTED: ("✔ accepted", "#137333"),
    OutcomeStatus.REJECTED: ("✘ rejected", "#c5221f"),
    OutcomeStatus.FAILED: ("✘ failed", "#c5221f"),
    OutcomeStatus.TIMEOUT: ("⏱ timeout", "#b06000"),
    OutcomeStatus.ERROR: ("⚠ error", "#c5221f"),
}


def ack_matrix(done: Dispatched) -> str:
    """Which vehicles accepted, rejected (with the reason), failed or timed out."""
    title = f"<div style='font-size:0.8em'><b>{html.escape(done.label)}</b></div>"
    if done.error:
        return (
            title
            + f"<div style='color:{css(ALERT_RGB)};font-size:0.8em'>{html.escape(done.error)}</div>"
        )
    outcomes = {}
    for res in done.results:
        outcomes.update(res.outcomes)
    errors = [e for res in done.results for e in res.errors]
    if not outcomes:
        return (
            title + f"<div style='color:{css(ALERT_RGB)};font-size:0.8em'>no vehicle answered</div>"
        )
    counts: dict[OutcomeStatus, int] = {}
    chips, problems = [], []
    for vid in sorted(outcomes):
        o = outcomes[vid]
        counts[o.status] = counts.get(o.status, 0) + 1
        text, color = _STATUS_STYLE[o.status]
        chips.append(
            f'<span data-vehicle="{vid}" data-status="{o.status.value}" title="{html.escape(text)} '
            f'{html.escape(o.reason)}" style="display:inline-block;min-width:2.6em;margin:1px;padding:0 3px;'
            f'border-radius:3px;color:white;background:{color};text-align:center">{vid} {text[0]}</span>'
        )
        if o.status is not OutcomeStatus.ACCEPTED:
            problems.append(
                f"<div><b>{vid}</b> <span style='color:{color}'>{text[2:]}</span>: {html.escape(o.reason)}</div>"
            )
    tally = " · ".join(f"{n} {s.value}" for s, n in counts.items())
    errs = "".join(f"<div>{html.escape(e)}</div>" for e in errors[:3])
    return (
        title
        + f"<div style='font-size:0.75em'>{tally}</div>"
        + f"<div style='font-size:0.75em;line-height:1.5'>{''.join(chips)}</div>"
        + f"<div style='font-size:0.75em'>{''.join(problems[:20])}{errs}</div>"
    )


_PROGRESS_COLOR = {
    Status.WAITING: "#777",
    Status.ACCEPTED: "#188038",
    Status.DONE: "#1e5e9e",
    Status.FAILED: "#c5221f",
    Status.REJECTED: "#c5221f",
    Status.SUPERSEDED: "#777",
    Status.TIMED_OUT: "#b06000",
    Status.UNREACHABLE: "#b06000",
}


def refused_line(counts: dict[str, int]) -> str:
    """One line for the command attempts refused in the last minute (by cause), or ""."""
    total = sum(counts.values())
    if not total:
        return ""
    causes = ", ".join(f"{n:,} {html.escape(cause)}" for cause, n in counts.items())
    return (
        f"<div data-refused-commands='{total}' style='color:{css(ALERT_RGB)};margin-bottom:3px'>"
        f"⚠ {total:,} refused command attempt{'s' if total != 1 else ''} in the last minute, "
        f"not shown: {causes}</div>"
    )


def command_log_html(
    entries: list[LoggedCommand],
    now_ns: int | None = None,
    present: Iterable[int] | None = None,
    answer_timeout_s: float = 5.0,
    refused: dict[str, int] | None = None,
    max_rows: int = 20,
    max_chips: int = 24,
    plans: list[PlanChange] | None = None,
) -> str:
    """Every command on the fleet from any station, newest first: who sent what to whom, and
    per vehicle whether it was accepted, is done (with its outcome), failed, was superseded,
    timed out or was not reachable. `refused`: command attempts refused in the last minute by
    cause (keyed mode), one line above the log that never displaces an entry. `plans`: the
    fleet plan versions followed (newest first), listed among the commands in arrival order."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    head = refused_line(refused or {})
    plans = plans or []
    if not entries and not plans:
        return (
            "<div style='font-size:0.75em;color:#777'>"
            f"{head}<div data-empty='1'>no commands yet: what any station sends shows here</div>"
            "</div>"
        )
    rows = []
    both: list[LoggedCommand | PlanChange] = [*entries, *plans]
    merged = sorted(both, key=lambda e: -e.seq)[:max_rows]
    for e in merged:
        if isinstance(e, PlanChange):
            rows.append(plan_change_html(e))
            continue
        when = time.strftime("%H:%M:%S", time.localtime(e.recv_ns / 1e9))
        shown = progress_all(e, now_ns, answer_timeout_s, present)
        chips: list[str] = []
        counts: dict[str, int] = {}
        for vid, pr in shown.items():
            name, color = pr.status.value, _PROGRESS_COLOR[pr.status]
            counts[name] = counts.get(name, 0) + 1
            if len(chips) < max_chips:
                label = f"{name}: {pr.detail}" if pr.detail else name
                chips.append(
                    f'<span data-vehicle="{vid}" data-answer="{name}" title="{html.escape(label)}" '
                    f'style="display:inline-block;margin:1px;padding:0 3px;border-radius:3px;'
                    f'color:white;background:{color}">{vid} {html.escape(label[:48])}</span>'
                )
        more = len(shown) - len(chips)
        summary = " · ".join(f"{n} {k}" for k, n in counts.items()) or "no answer yet"
        who_style = "" if e.signed or e.own else f"color:{css(ALERT_RGB)}"
        rows.append(
            f'<div data-command="{e.command.nonce}" data-station="{e.source_id}" '
            f'data-signed="{int(e.signed)}" style="margin-bottom:3px"><b>#{e.seq} {when}</b> '
            f"<span style='{who_style}'>{html.escape(e.sender())}</span>: "
            f"{html.escape(e.describe())} <span style='color:#555'>({summary})</span><br>"
            f"{''.join(chips)}{f' +{more} more' if more > 0 else ''}</div>"
        )
    return f"<div style='font-size:0.72em;line-height:1.35'>{head}{''.join(rows)}</div>"


def plan_change_html(change: PlanChange) -> str:
    """One plan version in the command log."""
    when = time.strftime("%H:%M:%S", time.localtime(change.recv_ns / 1e9))
    return (
        f'<div data-plan="{change.version}" data-own="{int(change.own)}" '
        f'style="margin-bottom:3px"><b>#{change.seq} {when}</b> '
        f"{html.escape(change.sender())}: {html.escape(change.describe())}</div>"
    )


_SEVERITY_COLOR = {0: "#777", 1: "#333", 2: "#b06000", 3: "#c5221f", 4: "#c5221f"}


def event_text(event: EventMessage, name_command: Callable[[int], str | None] | None = None) -> str:
    """What an event says, for the operator. An autopilot outcome names its command
    (`name_command`: nonce -> the command as the log shows it), never the raw nonce."""
    if not isinstance(event, ActionOutcome):
        return event.text
    outcome = event
    name = name_command(outcome.nonce) if name_command is not None else None
    word = "autopilot done" if outcome.ok else "autopilot FAILED"
    if name is None:
        return f"{word}: {outcome.detail}"
    return f"{word}: {name}" + ("" if outcome.ok else f": {outcome.detail}")


def event_log(
    events: list[tuple[str, EventMessage]], name_command: Callable[[int], str | None] | None = None
) -> str:
    """The latest events, newest first: (local time text, event)."""
    if not events:
        return "<div style='font-size:0.75em;color:#777'>no events yet</div>"
    rows = "".join(
        f"<div style='color:{_SEVERITY_COLOR.get(int(ev.severity), '#333')}'>{when} <b>{ev.vehicle_id}</b> "
        f"{html.escape(event_text(ev, name_command))}</div>"
        for when, ev in reversed(events)
    )
    return f"<div style='font-size:0.72em;line-height:1.3'>{rows}</div>"


def legend() -> str:
    chips = "".join(
        f'<span style="display:inline-block;margin:1px 4px 1px 0;white-space:nowrap">'
        f'<span style="display:inline-block;width:9px;height:9px;border-radius:5px;background:{css(rgb)};'
        f'margin-right:2px"></span>{mode.name.lower()}</span>'
        for mode, rgb in MODE_RGB.items()
    )
    return f"<div style='font-size:0.72em;line-height:1.3'>{chips}</div>"


def traffic_table(tracks: Iterable, now_s: float) -> str:
    """Traffic that does not cooperate (agent.traffic tracks): what it is, where, how fast, how
    old its last report is (red once stale)."""
    rows = []
    for t in tracks:
        n, e, d = (float(x) for x in t.at(now_s))
        age_s = max(0.0, now_s - t.stamp_s)
        kind = "manned" if t.manned else "unmanned"
        rows.append(
            "<tr>"
            + _td(f"<b style='color:{css(TRAFFIC_RGB)}'>{t.track_id:X}</b>", "left")
            + _td(f"{t.source.name.lower()} {kind}", "left")
            + _td(f"{n:.1f}")
            + _td(f"{e:.1f}")
            + _td(f"{-d:.1f}")
            + _td(f"{math.hypot(*t.vel_ned_m_s[:2]):.1f}")
            + _td(f"{age_s:.1f}", style=f"color:{css(ALERT_RGB)}" if age_s > 2.0 else "")
            + "</tr>"
        )
    if not rows:
        return "<i style='font-size:0.78em'>no traffic reported</i>"
    head = "".join(
        _TH.format(a=a, t=t)
        for a, t in (
            ("left", "track"),
            ("left", "what"),
            ("right", "N m"),
            ("right", "E m"),
            ("right", "alt m"),
            ("right", "m/s"),
            ("right", "age s"),
        )
    )
    return f"{_TABLE}<tr>{head}</tr>{''.join(rows)}</table>"
