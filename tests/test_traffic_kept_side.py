"""The kept side (policy/traffic_rules.py `kept_offset`, covey_safety.c's twin): against traffic
at least as fast as the vehicle, a vehicle inside the right-hand band on the other side of the
track that is already leaving it keeps that side instead of turning back across the track. Far
out, the track line swings with the traffic's heading, and vehicles 8-14 m off a manned
aircraft's track crossed it and reached only 27-29 m of the 30 m berth on fresh seeds."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import safety
from policy.traffic_rules import kept_offset, kept_offset_one
from tests.traffic_scenes import (
    assert_c_matches_numpy,
    intruder_run,
    three_paths,
    without_kept_side,
)

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
CFG = safety.SafetyConfig()


def test_the_offset_is_kept_only_when_leaving_the_track() -> None:
    # traffic 100 m behind (west, p = (0.5, -100)), eastbound at 20 m/s: m = 0.5 x 20 = 10;
    # pair distance 4 m: the band is 0.25 x 4 x 20 = 20 either side
    p, j, rv = (0.5, -100.0), (0.0, 20.0), (4.0, 1.0)
    still = kept_offset_one(*p, *j, 20.0, 0.0, 1.0, *rv)
    assert still == pytest.approx(10.0)
    # leaving southwards (away from it: p_n > 0 grows) at 1 m/s: where it will be on arrival
    away = kept_offset_one(*p, *j, 20.0, -1.0, 1.0, *rv)
    assert away == pytest.approx(10.0 + 100.0 / 19.0 * 20.0)
    # towards the track: as it is (the band may still send it across)
    assert kept_offset_one(*p, *j, 20.0, 1.0, 1.0, *rv) == pytest.approx(10.0)
    # on the other side (m < 0): as it is, leaving on that side or moving towards the track
    # no faster than guidance flies (up to 1.5 vmax off the track)
    assert kept_offset_one(-0.5, -100.0, *j, 20.0, 1.0, 1.0, *rv) == pytest.approx(-10.0)
    assert kept_offset_one(-0.5, -100.0, *j, 20.0, -1.4, 1.0, *rv) == pytest.approx(-10.0)
    # ... but escaping southwards at 1.6 m/s within the band: the track line swung across it
    assert kept_offset_one(-0.5, -100.0, *j, 20.0, -1.6, 1.0, *rv) == pytest.approx(
        -10.0 + 100.0 / 19.0 * 32.0
    )
    # beyond the band on the other side (m = -30 < -20): as it is, however fast it goes
    assert kept_offset_one(-1.5, -100.0, *j, 20.0, -1.9, 1.0, *rv) == pytest.approx(-30.0)
    # the traffic is ahead of us and going away (behind it): no arrival, as it is
    assert kept_offset_one(0.5, 100.0, *j, 20.0, -1.0, 1.0, *rv) == pytest.approx(10.0)
    # arrays equal floats
    rng = np.random.default_rng(5)
    a = rng.normal(0, 1, (6, 2000)) * np.array([[1], [100], [20], [20], [2], [2]])
    j_len = np.hypot(a[2], a[3])
    r = rng.uniform(3.0, 40.0, 2000)
    got = kept_offset(a[0], a[1], a[2], a[3], j_len, a[4], a[5], r, 1.0)
    want = [kept_offset_one(*a[:4, k], j_len[k], *a[4:, k], r[k], 1.0) for k in range(2000)]
    assert np.allclose(got, want, rtol=1e-12, atol=1e-9)
    swung = (a[0] * a[3] - a[1] * a[2] <= 0) & (got > a[0] * a[3] - a[1] * a[2] + 1e-9)
    assert swung.sum() >= 10, swung.sum()  # the draws reach the new branch


def _leaving(rng, away: bool):
    """A vehicle 0.3-1.2 m off a 10-30 m/s eastbound track (inside the band on the side the
    band would make it leave), the traffic 60-200 m behind; the vehicle flies east at 1 m/s and
    south (away from the track) at 0.5-1 m/s, or (`away` False) not sideways at all, and wants
    to go on that way at 1 m/s."""
    gap = rng.uniform(60.0, 200.0)
    off = rng.uniform(0.3, 1.2)
    speed = rng.uniform(10.0, 30.0)
    side = -rng.uniform(0.5, 1.0) if away else 0.0
    vel = np.array([side, 1.0])
    nbr_p = np.array([[off, -gap]])
    nbr_v = np.array([[0.0, speed]])
    pref = vel / np.hypot(*vel)  # at the cruise speed, as the policy asks
    return np.zeros(2), vel, pref, nbr_p, nbr_v, np.array([False])


def test_a_vehicle_leaving_the_track_keeps_its_side_a_still_one_takes_the_right() -> None:
    rng = np.random.default_rng(35)
    for _ in range(50):
        sc = _leaving(rng, away=True)
        a, b, c = three_paths(CFG, *sc)
        assert np.abs(a - b).max() <= 1e-9 and np.abs(a - c).max() <= 1e-9
        assert a[0] < 0.0, a  # on south, away from the track
    rng = np.random.default_rng(36)
    crossed = 0
    for _ in range(50):
        a, _, _ = three_paths(CFG, *_leaving(rng, away=False))
        crossed += bool(a[0] > 0.0)  # the band's right-hand leg: north, across the track
    assert crossed > 40


def test_without_it_the_leaving_vehicle_turns_back(monkeypatch) -> None:
    without_kept_side(monkeypatch)
    rng = np.random.default_rng(35)
    back = 0
    for _ in range(50):
        a, _, _ = three_paths(CFG, *_leaving(rng, away=True))
        back += bool(a[0] > 0.0)
    assert back > 10


@needs_cc
def test_c_keeps_the_side_as_numpy_does() -> None:
    rng = np.random.default_rng(37)
    assert_c_matches_numpy(CFG, (_leaving(rng, away=bool(k % 2)) for k in range(200)))


def _swung(rng):
    """A vehicle escaping south (towards m > 0) at 1.6-1.9 m/s from a 10-30 m/s eastbound track
    3-10 s behind it, which a swing of the track line has put 0.1-0.8 m north of the line (m < 0,
    inside the band); it wants to go on east at the cruise speed. The track is within the
    pair's horizon; nearer, where the vehicle will be still lies within the band, and the band's
    right-hand leg holds."""
    speed = rng.uniform(10.0, 30.0)
    gap = speed * rng.uniform(3.0, 10.0)
    off = rng.uniform(0.1, 0.8)
    vel = np.array([-rng.uniform(1.6, 1.9), 0.3])
    return (
        np.zeros(2),
        vel,
        np.array([0.0, 1.0]),
        np.array([[-off, -gap]]),
        np.array([[0.0, speed]]),
        np.array([False]),
    )


def test_an_escaping_vehicle_keeps_its_side_when_the_track_line_swings_across_it(
    monkeypatch,
) -> None:
    rng = np.random.default_rng(38)
    for _ in range(50):
        a, b, c = three_paths(CFG, *_swung(rng))
        assert np.abs(a - b).max() <= 1e-9 and np.abs(a - c).max() <= 1e-9
        assert a[0] < 0.0, a  # on south, the way it escapes
    from policy import traffic_rules

    monkeypatch.setattr(traffic_rules, "NC_KEEP_SIDE_SPEED_FACTOR", 1e9)  # before
    rng = np.random.default_rng(38)
    back = sum(bool(three_paths(CFG, *_swung(rng))[0][0] > 0.0) for _ in range(50))
    assert back >= 10  # the band's right-hand leg: back north, across the track


@needs_cc
def test_c_keeps_a_swung_side_as_numpy_does() -> None:
    rng = np.random.default_rng(39)
    assert_c_matches_numpy(CFG, (_swung(rng) for _ in range(200)))


# fresh seeds of `covey eval --suites manned --vehicles realistic` where a vehicle crossed the
# aircraft's track and entered the 30 m berth (27.4-28.8 m) before the kept side
ENTERED = (
    (155, "manned-40m_s-overtake", "policy+filter", "perfect"),
    (156, "manned-60m_s-circle-8", "policy+filter", "degraded"),
)


@pytest.mark.parametrize(("seed", "case", "controller", "link"), ENTERED)
def test_the_manned_berth_is_kept_where_a_vehicle_crossed_the_track(
    monkeypatch, seed: int, case: str, controller: str, link: str
) -> None:
    now = intruder_run(seed, case, controller, link, suite="manned")
    assert now["manned_entries"] == 0 and now["manned_min_sep"] >= 30.0, now["manned_min_sep"]
    without_kept_side(monkeypatch)
    before = intruder_run(seed, case, controller, link, suite="manned")
    assert before["manned_entries"] >= 1, before["manned_min_sep"]


@pytest.mark.slow
def test_a_track_line_that_swings_across_an_escaping_vehicle_does_not_turn_it_back(
    monkeypatch,
) -> None:
    # fresh seed 1208 of `covey eval --suites manned --vehicles
    # realistic:lag_s=0.45,gust_m_s=0.35`: a vehicle escaping at 1.9 m/s off a 20 m/s aircraft's
    # track, 440 m out, saw the track line swing 9 m across it (the aircraft's heading moved by
    # a degree in the gusts), turned back across the track and came to 28.8 m of it
    veh = "realistic:lag_s=0.45,gust_m_s=0.35"
    now = intruder_run(
        1208, "manned-20m_s-circle-8", "policy+filter", "degraded", "manned", None, veh
    )
    assert now["manned_entries"] == 0 and now["manned_min_sep"] >= 36.0, now["manned_min_sep"]
    from policy import traffic_rules

    monkeypatch.setattr(traffic_rules, "NC_KEEP_SIDE_SPEED_FACTOR", 1e9)  # before
    before = intruder_run(
        1208, "manned-20m_s-circle-8", "policy+filter", "degraded", "manned", None, veh
    )
    assert before["manned_entries"] >= 1, before["manned_min_sep"]
