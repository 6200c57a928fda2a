"""HTML for the fleet table, the ack matrix, the command log and the mode legend (pure: data
in, str out)."""

from __future__ import annotations

import html
import math
import time

from comms.commands import OutcomeStatus
from comms.schema import AckResult, Event
from groundstation.command_log import LoggedCommand
from groundstation.dispatch import Dispatched
from groundstation.fleet import FleetSnapshot, VehicleView
from groundstation.palette import ALERT_RGB, MODE_RGB, css, mode_rgb

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


def fleet_table(snap: FleetSnapshot, max_rows: int = 60, refused_states: int = 0) -> str:
    """One row per vehicle: id, mode, armed, N/E/alt, speed, battery, Hz, age, loss.
    `refused_states`: states the mesh refused (keyed mode), shown as a counter."""
    heads = [
        ("id", "right"),
        ("mode", "left"),
        ("arm", "center"),
        ("N m", "right"),
        ("E m", "right"),
        ("alt m", "right"),
        ("m/s", "right"),
        ("bat %", "right"),
        ("Hz", "right"),
        ("age s", "right"),
        ("loss %", "right"),
    ]
    rows = ["<tr>" + "".join(_TH.format(a=a, t=t) for t, a in heads) + "</tr>"]
    for v in snap.vehicles[:max_rows]:
        alert = v.too_close or (not v.alive and v.state) or v.unverified
        row_style = "background:#fde2e2" if alert else ""
        mode = _mode_badge(v)
        if v.unverified:  # keyed mode: states claiming this vehicle failed verification lately
            mode += (
                f" <b data-unverified='1' style='color:{css(ALERT_RGB)}'>UNVERIFIED "
                f"({html.escape(v.refused_cause)})</b>"
            )
        cells = [_td(f"<b>{v.vehicle_id}</b>"), _td(mode, "left")]
        s = v.state
        if s is None:
            cells += [_td("—", "center")] + [_td("")] * 5
        else:
            bat_style = f"color:{css(ALERT_RGB)};font-weight:bold" if s.battery_pct < 20 else ""
            cells += [
                _td("●" if s.armed else "○", "center"),
                _td(f"{s.pos_ned_m[0]:.1f}"),
                _td(f"{s.pos_ned_m[1]:.1f}"),
                _td(f"{v.alt_m:.1f}"),
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


_ANSWER_STYLE = {
    AckResult.ACCEPTED: ("accepted", "#188038"),
    AckResult.REJECTED: ("rejected", "#c5221f"),
    AckResult.FAILED: ("failed", "#b06000"),
}


def command_log_html(
    entries: list[LoggedCommand], own_station: int, max_rows: int = 20, max_chips: int = 24
) -> str:
    """Every command on the fleet from any station, newest first: who sent what to whom, and
    each vehicle's answer ("superseded" once a later accepted command replaced it there)."""
    if not entries:
        return "<div style='font-size:0.75em;color:#777'>no commands yet</div>"
    rows = []
    for e in entries[:max_rows]:
        when = time.strftime("%H:%M:%S", time.localtime(e.recv_ns / 1e9))
        who = "this station" if e.source_id == own_station else f"station {e.source_id}"
        chips, tally = [], {}
        for vid in sorted(e.answers):
            name, color = _ANSWER_STYLE.get(e.answers[vid].result, ("failed", "#b06000"))
            reason = e.answers[vid].reason
            done = e.done.get(vid)
            if done is not None and name == "accepted":  # the autopilot's part has ended
                name, color = ("done", "#1e7e34") if done.ok else ("failed", "#b06000")
                reason = done.detail
            if vid in e.superseded and name in ("accepted", "done"):
                name, color = "superseded", "#777"
            tally[name] = tally.get(name, 0) + 1
            if len(chips) < max_chips:
                reason = html.escape(reason)
                chips.append(
                    f'<span data-vehicle="{vid}" data-answer="{name}" title="{name} {reason}" '
                    f'style="display:inline-block;margin:1px;padding:0 3px;border-radius:3px;'
                    f'color:white;background:{color}">{vid} {name}</span>'
                )
        more = len(e.answers) - len(chips)
        summary = " · ".join(f"{n} {k}" for k, n in tally.items()) or "no answer yet"
        rows.append(
            f'<div data-command="{e.command.nonce}" data-station="{e.source_id}" '
            f'style="margin-bottom:3px"><b>{when}</b> {html.escape(who)}: '
            f"{html.escape(e.describe())} <span style='color:#555'>({summary})</span><br>"
            f"{''.join(chips)}{f' +{more} more' if more > 0 else ''}</div>"
        )
    return f"<div style='font-size:0.72em;line-height:1.35'>{''.join(rows)}</div>"


_SEVERITY_COLOR = {0: "#777", 1: "#333", 2: "#b06000", 3: "#c5221f", 4: "#c5221f"}


def event_log(events: list[tuple[str, Event]]) -> str:
    """The latest events, newest first: (local time text, event)."""
    if not events:
        return "<div style='font-size:0.75em;color:#777'>no events yet</div>"
    rows = "".join(
        f"<div style='color:{_SEVERITY_COLOR.get(int(ev.severity), '#333')}'>{when} <b>{ev.vehicle_id}</b> "
        f"{html.escape(ev.text)}</div>"
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
