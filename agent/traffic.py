"""Traffic in the guidance: the one point where tracks of vehicles that do not cooperate
(comms/traffic.py) join the neighbour snapshot an agent or a fleet simulator builds its
guidance's views from, each marked non-cooperative (the filter takes the whole correction for
it, not the reciprocal half) and, when manned, for the larger separation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from agent.backends.base import Traffic
from agent.neighbours import NeighbourSnapshot
from comms.traffic import TrafficTable, TrafficTrack, is_traffic_id


def merge_traffic(
    table: TrafficTable,
    nbrs: NeighbourSnapshot,
    now_s: float,
    own_pos_ned_m: np.ndarray | None = None,
) -> NeighbourSnapshot:
    """`nbrs` with the table's fresh tracks appended (in the vertical band of `own_pos_ned_m`
    when given), dead-reckoned to `now_s`, marked non-cooperative. No tracks: `nbrs` itself."""
    tracks = table.tracks(now_s)
    if own_pos_ned_m is not None:
        own_d = float(own_pos_ned_m[2])
        tracks = [t for t in tracks if abs(t.at(now_s)[2] - own_d) <= table.cfg.vertical_band_m]
    if not tracks:
        return nbrs
    return merge_tracks(nbrs, tracks, now_s, table.cfg.stale_s)


def merge_tracks(
    nbrs: NeighbourSnapshot, tracks: list[TrafficTrack], now_s: float, stale_s: float
) -> NeighbourSnapshot:
    """The neighbour snapshot with `tracks` appended as non-cooperative rows."""
    k = len(tracks)
    pos = np.array([t.at(now_s) for t in tracks], float).reshape(k, 3)
    vel = np.array([t.vel_ned_m_s for t in tracks], float).reshape(k, 3)
    hdg = np.arctan2(vel[:, 1], vel[:, 0])
    ages = np.array([max(0.0, now_s - t.stamp_s) for t in tracks], float)
    ids = tuple(t.neighbour_id for t in tracks)
    stale = tuple(i for i, a in zip(ids, ages, strict=True) if a > stale_s)
    n = len(nbrs)
    extra: dict[str, Any] = {}
    names = {f.name for f in dataclasses.fields(NeighbourSnapshot)}
    if "cooperative" in names:
        coop = getattr(nbrs, "cooperative", None)
        coop = np.ones(n, bool) if coop is None or len(coop) != n else np.asarray(coop, bool)
        extra["cooperative"] = np.concatenate([coop, np.zeros(k, bool)])
    if "manned" in names:
        manned = getattr(nbrs, "manned", None)
        manned = np.zeros(n, bool) if manned is None or len(manned) != n else manned
        extra["manned"] = np.concatenate([manned, [t.manned for t in tracks]]).astype(bool)
    return dataclasses.replace(
        nbrs,
        pos_ned_m=np.concatenate([np.asarray(nbrs.pos_ned_m, float).reshape(n, 3), pos]),
        vel_ned_m_s=np.concatenate([np.asarray(nbrs.vel_ned_m_s, float).reshape(n, 3), vel]),
        heading_rad=np.concatenate([np.asarray(nbrs.heading_rad, float).reshape(n), hdg]),
        ids=tuple(nbrs.ids) + ids,
        age_s=np.concatenate([np.asarray(nbrs.age_s, float).reshape(n), ages]),
        stale_ids=tuple(nbrs.stale_ids) + stale,
        seqs=tuple(nbrs.seqs) + (0,) * k if nbrs.seqs else (),
        **extra,
    )


def autopilot_traffic(nbrs: NeighbourSnapshot, table: TrafficTable, now_s: float) -> list[Traffic]:
    """`nbrs` (merged with `merge_traffic`) as the traffic an autopilot that flies around its
    neighbours itself is told of (onboard mode): covey vehicles cooperate, traffic does not,
    and the table's manned tracks are marked manned."""
    manned = {t.neighbour_id for t in table.tracks(now_s) if t.manned}
    return [
        Traffic(
            vid,
            tuple(p),
            tuple(v),
            float(h),
            float(a),
            cooperative=not is_traffic_id(vid),
            manned=vid in manned,
        )
        for vid, p, v, h, a in zip(
            nbrs.ids, nbrs.pos_ned_m, nbrs.vel_ned_m_s, nbrs.heading_rad, nbrs.age_s, strict=True
        )
    ]
