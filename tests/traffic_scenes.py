"""Shared by the traffic tests (tests/test_traffic_*.py): one vehicle's scene through numpy's
three filter paths, and through C beside numpy's reference, every position 1-sigma alike."""

from __future__ import annotations

import numpy as np

from policy import safety


def three_paths(cfg, pos, vel, pref, nbr_p, nbr_v, coop, sigma_m: float = 0.5):
    """(filter_one, filter_velocity, filter_padded) of the scene: the vehicle at pos with
    velocity vel wanting pref, neighbours nbr_p / nbr_v (K, 2), cooperative flags coop (K,)."""
    sig = np.full(len(nbr_p), sigma_m)
    a = safety.filter_one(
        pos,
        vel,
        pref,
        nbr_p,
        nbr_v,
        cfg,
        pos_sigma_m=sigma_m,
        nbr_pos_sigma_m=sig,
        nbr_cooperative=coop,
    )
    b = safety.filter_velocity(
        pos,
        vel,
        pref,
        nbr_p,
        nbr_v,
        cfg,
        pos_sigma_m=sigma_m,
        nbr_pos_sigma_m=sig,
        nbr_cooperative=coop,
    )
    c = safety.filter_padded(
        pos[None],
        vel[None],
        pref[None],
        nbr_p[None],
        nbr_v[None],
        np.ones((1, len(nbr_p)), bool),
        cfg,
        pos_sigma_m=np.array([sigma_m]),
        nbr_pos_sigma_m=sig[None],
        nbr_cooperative=coop[None],
    )[0]
    return a, b, c


def c_and_reference(c_filter, cfg, pos, vel, pref, nbr_p, nbr_v, coop, sigma_m: float = 0.5):
    """(C's result (firmware.csafety.CSafetyFilter.evaluate), numpy's filter_velocity) of the
    scene as `three_paths` takes it."""
    sig = np.full(len(nbr_p), sigma_m)
    r = c_filter.evaluate(
        pos, vel, pref, nbr_p, nbr_v, nbr_cooperative=coop, pos_sigma_m=sigma_m, nbr_pos_sigma_m=sig
    )
    ref = safety.filter_velocity(
        pos,
        vel,
        pref,
        nbr_p,
        nbr_v,
        cfg,
        nbr_cooperative=coop,
        pos_sigma_m=sigma_m,
        nbr_pos_sigma_m=sig,
    )
    return r, ref


def c_filter(cfg):
    """The C core's filter (firmware.csafety.CSafetyFilter) at `cfg`; needs a C compiler."""
    from firmware.cpolicy import load_library
    from firmware.csafety import CSafetyFilter

    return CSafetyFilter(load_library(), cfg)
