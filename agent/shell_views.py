"""What one shell's guided rows see of the world: `NeighbourViews` (agent/guidance.py) of
the shell's own vehicles and the others in the neighbour table, nearest first.

One vehicle (an agent's every tick) takes `_one_vehicle_views`, and where every neighbour is
kept and there is no traffic, `_all_kept_views`: the same arrays with a fraction of the array
calls (a cold tick pays for each, docs/companion.md). `neighbour_views_rows` is the general
path and their reference (tests/test_shell_views.py).
"""

from __future__ import annotations

import functools

import numpy as np

from agent.flight_core import AIRBORNE_MODES, FlightCore, Observed
from agent.guidance import NeighbourViews
from agent.neighbours import NeighbourSnapshot
from agent.shell_rows import F8, stale_mask
from kit.masks import mode_mask

_AIRBORNE = mode_mask(AIRBORNE_MODES)


def neighbour_views(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    ext: NeighbourSnapshot,
    rows: np.ndarray,
    max_neighbours: int | None,
) -> NeighbourViews:
    """What each guided row sees: the nearest `max_neighbours` airborne vehicles, the shell's
    own (`obs`, position 1-sigmas `pos_sigma_m`) and the others in `ext` (dead-reckoned from
    their last state, traffic included, stale as `ext.stale_ids` says).

    One vehicle (an agent's every tick) takes `_one_vehicle_views`, which builds the same
    views with a fraction of the array operations; `neighbour_views_rows` is the general path
    and its reference (tests compare them)."""
    if len(ids) == 1:
        views = _one_vehicle_views(core, obs, pos_sigma_m, ids, ext, rows, max_neighbours)
        if views is not None:
            return views
    return neighbour_views_rows(core, obs, pos_sigma_m, ids, ext, rows, max_neighbours)


def neighbour_views_rows(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    ext: NeighbourSnapshot,
    rows: np.ndarray,
    max_neighbours: int | None,
) -> NeighbourViews:
    """`neighbour_views` of any number of rows: the shell's vehicles and `ext` as one world,
    each row's nearest chosen by NeighbourViews.nearest."""
    n = len(ids)
    airborne = _AIRBORNE[core.mode] & obs.armed
    sigma = np.concatenate([pos_sigma_m, ext.column("pos_sigma_m", 0.0)])
    coop = np.concatenate([np.ones(n, bool), ext.column("cooperative", True)])
    manned = np.concatenate([np.zeros(n, bool), ext.column("manned", False)])
    # none of them when every position is exact and everyone cooperates (the plain views)
    sky: dict[str, np.ndarray] = {}
    if sigma.any():
        sky["world_pos_sigma_m"] = sigma
        sky["rows_pos_sigma_m"] = sigma[rows]
    if not coop.all():
        sky["world_cooperative"] = coop
    if manned.any():
        sky["world_manned"] = manned
    return NeighbourViews.nearest(
        obs.pos_m[rows],
        rows,
        np.concatenate([obs.pos_m, ext.pos_ned_m]),
        np.concatenate([obs.vel_m_s, ext.vel_ned_m_s]),
        np.concatenate([core.heading_rad, ext.heading_rad]),
        np.concatenate([airborne, np.ones(len(ext), bool)]),
        np.concatenate([np.zeros(n, bool), stale_mask(ext)]),
        max_neighbours,
        np.concatenate([ids, np.array(ext.ids, np.int64)]),
        ids[rows],
        **sky,
    )


def _one_vehicle_views(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    ext: NeighbourSnapshot,
    rows: np.ndarray,
    max_neighbours: int | None,
) -> NeighbourViews | None:
    """`neighbour_views_rows` of one vehicle (rows [0]), array for array: its world is the
    vehicle (entry 0, never its own neighbour: its key is inf, whether airborne or not)
    followed by `ext`. All of it is taken, in order, when `max_neighbours` allows (the
    vehicle stays in as an invalid entry, as there), else the same argpartition of the same
    keys chooses (all kept and no traffic columns, an agent's common case: `_all_kept_views`).
    None where the inputs are not the plain ones (float64 positions, shapes that agree, a
    width > 0): the general path answers them."""
    k = len(ext.ids)
    m = k + 1
    width = m if max_neighbours is None else min(max_neighbours, m)
    own, at = obs.pos_m, ext.pos_ned_m
    try:
        plain = (
            width > 0
            and len(rows) == 1
            and rows[0] == 0
            and own.shape == (1, 3)
            and own.dtype == F8
            and at.shape == (k, 3)
            and at.dtype == F8
            and obs.vel_m_s.shape == (1, 3)
            and ext.vel_ned_m_s.shape == (k, 3)
            and core.heading_rad.shape == (1,)
            and ext.heading_rad.shape == (k,)
            and pos_sigma_m.shape == (1,)
        )
    except AttributeError:  # not arrays
        return None
    if not plain:
        return None
    if width == m and ext.cooperative is None and ext.manned is None:
        views = _all_kept_views(core, obs, pos_sigma_m, ids, ext)
        if views is not None:
            return views
    # squared horizontal distances, as NeighbourViews.nearest computes them
    d = own[0, :2] - at[:, :2]
    np.square(d, out=d)
    key = np.empty((1, m))
    key[0, 0] = np.inf
    np.add(d[:, 0], d[:, 1], out=key[0, 1:])
    if width < m:
        cols = key.argpartition(width - 1, axis=1)[:, :width]  # np.argpartition's own call
        valid = np.isfinite(key[0][cols])  # take_along_axis of the one row

        def pick(world: np.ndarray) -> np.ndarray:
            return world[cols]

    else:  # all of them: (1, m) of the world as it is
        valid = np.isfinite(key)

        def pick(world: np.ndarray) -> np.ndarray:
            return world[None]

    if ext.stale_ids:
        stale = pick(np.concatenate([np.zeros(1, bool), stale_mask(ext)])) & valid
    else:
        stale = np.zeros((1, width), bool)
    world_ids = np.concatenate([ids, np.array(ext.ids, np.int64)])
    # the sky's columns as neighbour_views_rows gives them to NeighbourViews.nearest
    got = ext.pos_sigma_m
    if got is None:
        sigma = None  # all 0
    elif type(got) is np.ndarray and got.dtype == F8 and got.shape == (k,):
        sigma = got  # what column() would copy
    else:
        sigma = ext.column("pos_sigma_m", 0.0)
    nbr_sigma = own_sigma = coop = manned = None
    if np.count_nonzero(pos_sigma_m) or (sigma is not None and np.count_nonzero(sigma)):
        if sigma is None:
            sigma = ext.column("pos_sigma_m", 0.0)
        world_sigma = np.concatenate([pos_sigma_m, sigma])
        nbr_sigma = pick(np.asarray(world_sigma, float))
        own_sigma = np.asarray(world_sigma[rows], float)
    if ext.cooperative is not None:
        world_coop = np.concatenate([np.ones(1, bool), ext.column("cooperative", True)])
        if not world_coop.all():
            coop = pick(np.asarray(world_coop, bool))
    if ext.manned is not None:
        world_manned = np.concatenate([np.zeros(1, bool), ext.column("manned", False)])
        if world_manned.any():
            manned = pick(np.asarray(world_manned, bool))
    return NeighbourViews(
        pick(np.concatenate([own, at])),
        pick(np.concatenate([obs.vel_m_s, ext.vel_ned_m_s])),
        pick(np.concatenate([core.heading_rad, ext.heading_rad])),
        valid,
        stale,
        pick(np.asarray(world_ids, np.int64)),
        np.asarray(ids[rows], np.int64),
        nbr_sigma,
        coop,
        own_sigma,
        manned,
    )


def _all_kept_views(
    core: FlightCore,
    obs: Observed,
    pos_sigma_m: np.ndarray,
    ids: np.ndarray,
    ext: NeighbourSnapshot,
) -> NeighbourViews | None:
    """`_one_vehicle_views` where every entry is kept and `ext` has no traffic columns (an
    agent's every tick), with one array for all the floats: the world's positions, sigmas,
    velocities and headings one after the other, each field a read-only view of its part
    (the values of the general path's concatenations, bit for bit). Every entry but the
    vehicle's own is valid when each |coordinate| < 1e150: then key = dn^2 + de^2 < 2e300 is
    finite. None where that or the float64 inputs do not hold: the array path answers."""
    k = len(ext.ids)
    m = k + 1
    sigma = ext.pos_sigma_m
    if sigma is None:
        sigma = np.zeros(k)  # column()'s fill
    if not (
        type(sigma) is np.ndarray
        and sigma.dtype is F8
        and sigma.shape == (k,)
        and pos_sigma_m.dtype is F8
        and obs.vel_m_s.dtype is F8
        and ext.vel_ned_m_s.dtype is F8
        and core.heading_rad.dtype is F8
        and ext.heading_rad.dtype is F8
        and type(ids) is np.ndarray
        and ids.shape == (1,)
        and ids.dtype.kind == "i"
    ):
        return None
    # the parts' bytes joined: plain copies, where np.concatenate's dtype and casting set-up
    # cost twice as much cold (tobytes is in C order, as concatenate flattens)
    flat = np.frombuffer(
        b"".join(
            (
                obs.pos_m.tobytes(),
                ext.pos_ned_m.tobytes(),
                pos_sigma_m.tobytes(),
                sigma.tobytes(),
                obs.vel_m_s.tobytes(),
                ext.vel_ned_m_s.tobytes(),
                core.heading_rad.tobytes(),
                ext.heading_rad.tobytes(),
            )
        ),
        F8,
    )
    head = flat[: 4 * m].tolist()  # positions, then sigmas
    if not sum(map(abs, head)) < 1e150:  # NaN, inf or huge somewhere
        return None
    nbr_sigma = own_sigma = None
    if any(head[3 * m :]):  # count_nonzero's answer: NaN counts, -0.0 does not
        nbr_sigma = flat[3 * m : 4 * m].reshape(1, m)
        own_sigma = flat[3 * m : 3 * m + 1]
    valid, stale = _all_but_own(m)
    if ext.stale_ids:
        old = set(ext.stale_ids)
        stale = np.array([[False, *[v in old for v in ext.ids]]], bool)
    world_ids = np.array([[ids.item(0), *ext.ids]], np.int64)
    return NeighbourViews(
        flat[: 3 * m].reshape(1, m, 3),
        flat[4 * m : 7 * m].reshape(1, m, 3),
        flat[7 * m :].reshape(1, m),
        valid,
        stale,
        world_ids,
        world_ids[0, :1],
        nbr_sigma,
        None,
        own_sigma,
        None,
    )


@functools.lru_cache(maxsize=64)
def _all_but_own(m: int) -> tuple[np.ndarray, np.ndarray]:
    """(valid, stale) (1, m) of a one-vehicle world that is all kept: every entry but the
    vehicle's own (entry 0) valid, none stale. Read-only: every tick's views share them."""
    valid = np.ones((1, m), bool)
    valid[0, 0] = False
    stale = np.zeros((1, m), bool)
    valid.flags.writeable = stale.flags.writeable = False
    return valid, stale
