"""The C core's arguments, kept from call to call and refilled (firmware/csafety.py
`CSafetyFilter`, `VehicleRows`; firmware/cpolicy.py `CPolicy`), against the arguments built
anew field by field, the reference: the same bytes reach the core, so the same answers come
back, whatever the calls before left in the kept rows."""

from __future__ import annotations

import ctypes
import shutil

import numpy as np
import pytest

from firmware import csafety
from firmware.csafety import MAX_INPUTS, TRACK_DTYPE, VEHICLE_DTYPE
from policy.observation import Observation, Sky

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def _tracks_by_field(pos_m, vel_m_s, ids=None, sigma=None, coop=None, manned=None) -> np.ndarray:
    """covey_track_t rows written field by field: the reference of `fill_tracks`."""
    pos = np.asarray(pos_m, dtype=np.float64).reshape(-1, 2)
    vel = np.asarray(vel_m_s, dtype=np.float64).reshape(-1, 2)
    t = np.zeros(len(pos), TRACK_DTYPE)
    t["pos_n_m"], t["pos_e_m"] = pos[:, 0], pos[:, 1]
    t["vel_n_m_s"], t["vel_e_m_s"] = vel[:, 0], vel[:, 1]
    t["id"] = 0 if ids is None else np.asarray(ids, dtype=np.int64).reshape(-1)
    t["pos_sigma_m"] = 0.0 if sigma is None else np.asarray(sigma, np.float64)
    if coop is not None or manned is not None:
        t["non_cooperative"] = csafety.track_kinds(len(pos), coop, manned)
    return t


def _vehicles_by_field(
    obs: Observation, now_us: int, stamp_s=None, nbr_stamp_s=None
) -> tuple[np.ndarray, np.ndarray]:
    """covey_vehicle_t rows written field by field: the reference of `VehicleRows.fill`."""
    k = obs.nbr_pos_m.shape[0]
    own = np.zeros(1, VEHICLE_DTYPE)
    own["pos_n_m"], own["pos_e_m"] = obs.pos_m[0], obs.pos_m[1]
    own["heading_rad"] = obs.heading_rad
    own["stamp_us"] = now_us if stamp_s is None else csafety.micros(stamp_s)
    nb = np.zeros(max(k, 1), VEHICLE_DTYPE)
    nb["pos_n_m"][:k], nb["pos_e_m"][:k] = obs.nbr_pos_m[:, 0], obs.nbr_pos_m[:, 1]
    nb["heading_rad"][:k] = obs.nbr_heading_rad
    nb["stamp_us"][:k] = (
        now_us if nbr_stamp_s is None else np.round(np.asarray(nbr_stamp_s) * 1e6).astype(np.uint64)
    )
    return own, nb


def _policy_args(s: dict) -> tuple:
    """`_scene`'s inputs as CPolicy.command / Observation.shaped take them."""
    nbrs = (s["nbr_pos_m"], s["nbr_vel_m_s"], s["nbr_heading_rad"])
    return (s["pos_m"], s["vel_m_s"], 0.4, s["goal_m"], *nbrs)


def _scene(rng, k: int, sky: bool = True) -> dict:
    """One vehicle among k neighbours, the inputs in the forms callers give them."""
    pos = rng.normal(0.0, 2.0, 2)
    scene = {
        "pos_m": pos,
        "vel_m_s": rng.normal(0.0, 0.8, 2),
        "pref_m_s": rng.normal(0.5, 0.8, 2),
        "goal_m": pos + rng.normal(30.0, 10.0, 2),
        "nbr_pos_m": pos + rng.normal(0.0, 6.0, (k, 2)),
        "nbr_vel_m_s": rng.normal(0.0, 0.8, (k, 2)),
        "nbr_heading_rad": rng.uniform(-np.pi, np.pi, k),
        "nbr_ids": rng.integers(1, 2**31, k),
        "sky": {},
    }
    if sky:
        coop = rng.random(k) < 0.8
        scene["sky"] = {
            "pos_sigma_m": float(rng.uniform(0.0, 0.8)),
            "nbr_pos_sigma_m": rng.uniform(0.0, 0.8, k),
            "nbr_cooperative": coop,
            "nbr_manned": ~coop & (rng.random(k) < 0.5),
        }
    return scene


def test_the_track_struct_and_the_track_rows_agree() -> None:
    """TrackC (the own track) and TRACK_DTYPE (the neighbours' rows) are one covey_track_t:
    seven 4-byte fields, unpadded, as `track_columns` views them."""
    layout = [(n, getattr(csafety.TrackC, n).offset) for n, _ in csafety.TrackC._fields_]
    assert layout == [(n, TRACK_DTYPE.fields[n][1]) for n in TRACK_DTYPE.names]
    assert ctypes.sizeof(csafety.TrackC) == TRACK_DTYPE.itemsize == 7 * 4
    own = csafety.own_track((1.5, -2.0), (0.25, 0.5), 7, 0.75)
    row = csafety.tracks([[1.5, -2.0]], [[0.25, 0.5]], [7], [0.75])
    assert bytes(own) == row.tobytes()


def test_pair_floats_takes_every_form_of_a_pair() -> None:
    for xy in ((1.5, -2.25), [1.5, -2.25], np.array([1.5, -2.25]), np.array([[1.5, -2.25]])):
        assert list(csafety.pair_floats(xy)) == [1.5, -2.25]
    assert list(csafety.pair_floats(np.array([3, 4], np.int32))) == [3.0, 4.0]
    with pytest.raises(ValueError):
        csafety.pair_floats([1.0, 2.0, 3.0])


@pytest.mark.parametrize("seed", range(4))
def test_fill_tracks_writes_the_bytes_field_by_field_writes(seed: int) -> None:
    """Column blocks of the float32 / uint32 views, over a buffer that earlier calls filled:
    the rows written hold exactly the reference's bytes, for arrays, lists, scalars, Nones."""
    rng = np.random.default_rng(seed)
    buf = np.zeros(MAX_INPUTS, TRACK_DTYPE)

    def pick(*options):
        return options[int(rng.integers(len(options)))]

    for _ in range(50):
        k = int(rng.integers(0, MAX_INPUTS + 1))
        pos = rng.normal(0.0, 1e3, (k, 2))
        vel = rng.normal(0.0, 3.0, (k, 2))
        ids = pick(None, rng.integers(-5, 2**33, k), rng.integers(0, 9, k).tolist(), 7)
        sigma = pick(None, rng.uniform(0, 2, k), 0.25, rng.uniform(0, 2, k).tolist())
        coop = pick(None, rng.random(k) < 0.5, False)
        manned = pick(None, rng.random(k) < 0.3)
        if rng.random() < 0.3:  # views of wider arrays, as an agent's views give them
            pos = np.concatenate([pos, np.zeros((k, 1))], axis=1)[:, :2]
            vel = vel.tolist()
        got = csafety.fill_tracks(buf, pos, vel, ids, sigma, coop, manned)
        want = _tracks_by_field(pos, vel, ids, sigma, coop, manned)
        assert got.tobytes() == want.tobytes()
    with pytest.raises(ValueError):
        csafety.fill_tracks(buf, np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError):
        csafety.fill_tracks(buf, np.zeros((MAX_INPUTS + 1, 2)), np.zeros((MAX_INPUTS + 1, 2)))


@pytest.mark.parametrize("seed", range(3))
def test_vehicle_rows_write_the_bytes_field_by_field_writes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    kept = csafety.VehicleRows()
    for _ in range(40):
        k = int(rng.integers(0, MAX_INPUTS + 1))
        s = _scene(rng, k, sky=False)
        obs = Observation.shaped(*_policy_args(s))
        now_us = int(rng.integers(0, 2**40))
        stamps = (None, None) if rng.random() < 0.5 else (9.25, rng.uniform(0.0, 10.0, k))
        own, nb = _vehicles_by_field(obs, now_us, *stamps)
        assert kept.fill(obs, now_us, *stamps) == k
        assert kept.own.tobytes() == own.tobytes()
        assert kept.nbrs[:k].tobytes() == nb[:k].tobytes()
        fresh = csafety.vehicles(obs, now_us, *stamps)
        assert fresh[0].tobytes() == own.tobytes() and fresh[1].tobytes() == nb.tobytes()
    with pytest.raises(ValueError):
        kept.fill(obs, 0, None, np.zeros(k + 1))


@pytest.fixture(scope="module")
def cpol():
    from firmware.cpolicy import CPolicy

    return CPolicy.load()


def _filter_fresh(filt, s: dict, pref_m_s) -> tuple[int, float, float]:
    """covey_safety_filter on arguments built anew (the reference of the kept ones)."""
    sky = s["sky"]
    t = _tracks_by_field(
        s["nbr_pos_m"],
        s["nbr_vel_m_s"],
        s["nbr_ids"],
        sky.get("nbr_pos_sigma_m"),
        sky.get("nbr_cooperative"),
        sky.get("nbr_manned"),
    )
    out = csafety.SafetyOutC()
    own = csafety.TrackC(*s["pos_m"], *s["vel_m_s"], 1, sky.get("pos_sigma_m", 0.0), 0)
    st = filt._lib.covey_safety_filter(
        ctypes.byref(csafety.SafetyConfigC.of(filt.cfg)),
        ctypes.byref(own),
        (ctypes.c_float * 2)(*pref_m_s),
        np.ascontiguousarray(t).ctypes.data if len(t) else np.zeros(1, TRACK_DTYPE).ctypes.data,
        len(t),
        ctypes.create_string_buffer(filt._lib.covey_safety_scratch_bytes()),
        ctypes.byref(out),
    )
    return st, out.vel_n_m_s, out.vel_e_m_s


def test_the_kept_filter_arguments_answer_as_fresh_ones(cpol) -> None:
    """`CSafetyFilter.velocity` (floats, tuples in) and `evaluate` (arrays in) on the kept,
    refilled arguments equal a call on arguments built anew, call after call, the number of
    neighbours going up and down."""
    filt = cpol._filter
    rng = np.random.default_rng(11)
    moved = 0
    for _ in range(120):
        s = _scene(rng, int(rng.integers(0, 30)), sky=rng.random() < 0.7)
        pref = s["pref_m_s"]
        st, vn, ve = _filter_fresh(filt, s, pref)
        assert st == 0
        nbrs = (s["nbr_pos_m"], s["nbr_vel_m_s"], 1, s["nbr_ids"])
        own = (tuple(s["pos_m"].tolist()), tuple(s["vel_m_s"].tolist()), tuple(pref.tolist()))
        assert filt.velocity(*own, *nbrs, **s["sky"]) == ("ok", vn, ve)
        r = filt.evaluate(s["pos_m"], s["vel_m_s"], pref, *nbrs, **s["sky"])
        assert r.status == "ok" and r.vel_m_s.tolist() == [vn, ve]
        moved += bool(np.abs(r.vel_m_s - pref).max() > 1e-6)
    assert moved > 20, "the scenes must make the filter act"
    bad = filt.velocity((np.nan, 0.0), (0.0, 0.0), (0.0, 0.0), np.zeros((1, 2)), np.zeros((1, 2)))
    assert bad[0] == "nonfinite"


def test_the_kept_sparse_arguments_answer_as_fresh_ones(cpol) -> None:
    """`CSafetyFilter.sparse` / `sparse_velocity` on the filter's kept tracks equal
    covey_sparse_choose on arguments built anew (no ids, as policy.sparse takes them)."""
    filt = cpol._filter
    rng = np.random.default_rng(12)
    straight = 0
    for _ in range(120):
        s = _scene(rng, int(rng.integers(0, 5)), sky=rng.random() < 0.5)
        s["nbr_pos_m"] = s["pos_m"] + rng.normal(0.0, 12.0, s["nbr_pos_m"].shape)
        sky = s["sky"]
        t = _tracks_by_field(
            s["nbr_pos_m"],
            s["nbr_vel_m_s"],
            None,
            sky.get("nbr_pos_sigma_m"),
            sky.get("nbr_cooperative"),
            sky.get("nbr_manned"),
        )
        out = csafety.SparseOutC()
        own = csafety.TrackC(*s["pos_m"], *s["vel_m_s"], 0, sky.get("pos_sigma_m", 0.0), 0)
        st = filt._lib.covey_sparse_choose(
            ctypes.byref(csafety.SafetyConfigC.of(filt.cfg)),
            ctypes.byref(own),
            (ctypes.c_float * 2)(*s["goal_m"]),
            (ctypes.c_float * 2)(*s["pref_m_s"]),
            np.zeros(1, TRACK_DTYPE).ctypes.data if not len(t) else t.ctypes.data,
            len(t),
            ctypes.create_string_buffer(filt._lib.covey_safety_scratch_bytes()),
            ctypes.byref(out),
        )
        args = (s["pos_m"], s["vel_m_s"], s["goal_m"], s["pref_m_s"])
        got = filt.sparse(*args, s["nbr_pos_m"], s["nbr_vel_m_s"], **sky)
        assert st == 0 and (got.status, got.vel_m_s.tolist()) == (
            "ok",
            [out.vel_n_m_s, out.vel_e_m_s],
        )
        assert (got.straight, got.n_encounters) == (bool(out.straight), out.n_encounters)
        v = tuple(s["pref_m_s"].tolist())
        assert filt.sparse_velocity(*args[:3], v, s["nbr_pos_m"], s["nbr_vel_m_s"], **sky) == (
            "ok",
            out.vel_n_m_s,
            out.vel_e_m_s,
        )
        straight += got.straight
    assert 10 < straight < 110, "the scenes must take both answers"


def test_the_kept_policy_arguments_answer_as_fresh_ones(cpol) -> None:
    """`CPolicy.evaluate` on its kept rows equals covey_command on rows built anew, and
    `preferred` / `command` on a long-lived CPolicy equal a fresh CPolicy's, call after call."""
    from firmware.cpolicy import CPolicy

    rng = np.random.default_rng(13)
    for i in range(40):
        s = _scene(rng, int(rng.integers(0, 45)), sky=i % 2 == 0)
        args = _policy_args(s)
        sky = Sky.checked(**{**s["sky"], "k": len(s["nbr_pos_m"])}) if s["sky"] else Sky()
        obs = Observation.shaped(*args, sky)
        own, nb = _vehicles_by_field(obs, 0)
        out = csafety.CommandC()
        st = cpol._lib.covey_command(
            ctypes.byref(cpol._cfg),
            own.ctypes.data,
            np.asarray(obs.goal_m, np.float32).ctypes.data,
            nb.ctypes.data,
            len(obs.nbr_pos_m),
            0,
            ctypes.create_string_buffer(cpol._lib.covey_scratch_bytes()),
            ctypes.byref(out),
        )
        r = cpol.evaluate(obs)
        assert (r.status, r.vel_m_s.tolist()) == ("ok", [out.vel_n_m_s, out.vel_e_m_s]) and st == 0
        assert r.action.tolist() == list(out.action) and r.n_used == out.n_used
        if i % 8 == 0:
            fresh = CPolicy.load()
            for call in ("preferred", "command"):
                want = getattr(fresh, call)(*args, **s["sky"])
                assert getattr(cpol, call)(*args, **s["sky"]).tolist() == want.tolist()
