"""The escape's clear speed (policy/traffic_rules.py `clear_speed`, covey_safety.c's escape
line): within the berth of a faster intruder that closes from behind, the vehicle leaves its
track fast enough to clear the berth before the intruder arrives, not at a fixed 0.8 x its
cruise speed. Numpy and C agree (tests/test_traffic_escape_speed.py's parity scenes cross the
same line; here the C filter on scenes built for it)."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from policy import traffic_rules
from policy.traffic_rules import NC_CLEAR_SHARE, NC_ESCAPE_SHARE, clear_speed
from tests.traffic_scenes import assert_c_matches_numpy, three_paths

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def test_clear_speed_is_the_share_unless_more_is_needed() -> None:
    vmax = 1.0
    base = NC_ESCAPE_SHARE * vmax
    # not behind us, or not gaining: the fixed share
    assert clear_speed(0.0, -2.0, 1.0, 6.0, vmax, 2.0) == pytest.approx(base)
    assert clear_speed(0.0, 4.0, 0.0, 6.0, vmax, 2.0) == pytest.approx(base)
    # 6 m to clear, it arrives in 4 s: 1.5 m/s
    assert clear_speed(0.0, 4.0, 1.0, 6.0, vmax, 2.0) == pytest.approx(1.5)
    # already 5.5 m off: the share is enough
    assert clear_speed(5.5, 4.0, 1.0, 6.0, vmax, 2.0) == pytest.approx(base)
    # more than the escape speed allows: capped below where the rest of it, along the track,
    # gains the most (a 2 m/s intruder: escape speed 2, vmax 1 along its track, sqrt(3) across)
    cap = NC_CLEAR_SHARE * math.sqrt(3.0)
    assert clear_speed(0.0, 1.0, 1.0, 6.0, vmax, 2.0) == pytest.approx(cap)
    # a very fast one (10 m/s): little is gained along its track (4 / 10 m/s of 2 is best)
    far = NC_CLEAR_SHARE * math.sqrt(4.0 - 0.4**2)
    assert clear_speed(0.0, 1.0, 1.0, 6.0, vmax, 10.0) == pytest.approx(far)
    # arrays, as the filter's padded path takes them
    got = clear_speed(np.zeros(2), np.array([4.0, -1.0]), np.ones(2), 6.0, vmax, np.full(2, 2.0))
    assert got.tolist() == pytest.approx([1.5, base])


def _overtaken(rng):
    """A vehicle flying east at 1 m/s, an intruder 1.5-3.4 m behind on nearly its line at
    1.5-2.5 m/s: inside the 3.6 m berth, closing."""
    pos = np.zeros(2)
    vel = np.array([0.0, 1.0])
    gap = rng.uniform(1.5, 3.4)
    nbr_p = np.array([[rng.uniform(-0.5, 0.5), -gap]])
    nbr_v = np.array([[0.0, rng.uniform(1.5, 2.5)]])
    return pos, vel, vel.copy(), nbr_p, nbr_v, np.array([False])


def test_an_overtaken_vehicle_steps_off_faster_than_the_share() -> None:
    from policy import safety

    cfg = safety.SafetyConfig()
    rng = np.random.default_rng(37)
    faster = 0
    for _ in range(100):
        pos, vel, pref, nbr_p, nbr_v, coop = _overtaken(rng)
        v = safety.filter_velocity(pos, vel, pref, nbr_p, nbr_v, cfg, nbr_cooperative=coop)
        lateral = abs(float(v[0]))  # off the intruder's (eastbound) track
        assert lateral >= NC_ESCAPE_SHARE * cfg.max_speed_m_s - 1e-6
        faster += lateral > NC_ESCAPE_SHARE * cfg.max_speed_m_s + 0.1
    assert faster > 50


def test_the_lateral_cap_gains_the_most_room() -> None:
    """The cap sqrt(V^2 - b^2) is where a / (c - b(a)), the lateral room gained per metre the
    intruder closes, peaks over a grid of lateral speeds a (b(a) = min(b, sqrt(V^2 - a^2)), b
    the speed kept along its track), times NC_CLEAR_SHARE, and never below the fixed share:
    overtaken at vmax (b up to vmax) and met head-on (b 0: all of V sideways)."""
    vmax = 1.0
    for c in (1.2, 1.5, 1.875, 2.5, 3.0, 5.0):
        speed = min(2.0 * vmax, max(vmax, c))
        a = np.linspace(0.0, speed * (1 - 1e-9), 20001)
        for own_along in (vmax, 0.5 * vmax, -vmax):
            keep = min(max(own_along, 0.0), vmax)
            b = np.minimum(keep, np.sqrt(speed * speed - a * a))
            best = float(a[np.argmax(a / (c - b))])
            # need is huge (r 1e6): the cap
            cap = float(clear_speed(0.0, 1.0, c - own_along, 1e6, vmax, c))
            want = max(NC_ESCAPE_SHARE * vmax, NC_CLEAR_SHARE * best)  # the floor too
            assert cap == pytest.approx(want, abs=1e-3), (c, own_along)
    # met head-on: the whole escape speed's share, as before the cap
    assert clear_speed(0.0, 1.0, 3.0, 1e6, vmax, 2.0) == pytest.approx(NC_CLEAR_SHARE * 2.0)


def test_numpys_three_paths_agree() -> None:
    """filter_one (the agents' single-vehicle path, traffic_rules.escape_one), filter_velocity
    and filter_padded (traffic_rules.escape) give the same escape."""
    from policy import safety

    cfg = safety.SafetyConfig()
    rng = np.random.default_rng(39)
    for _ in range(200):
        one, many, padded = three_paths(cfg, *_overtaken(rng))
        assert np.abs(one - many).max() <= 1e-9 and np.abs(padded - many).max() <= 1e-9


@needs_cc
def test_c_steps_off_as_numpy_does() -> None:
    from policy import safety

    rng = np.random.default_rng(38)
    assert_c_matches_numpy(safety.SafetyConfig(), (_overtaken(rng) for _ in range(200)))


def _overtakes(warn_s: float, links: tuple[str, ...], heard: bool = False) -> list[float]:
    """The closest true approach of each of bench/late_intruder.py's overtakes at 1.5x and 2x,
    the intruder appearing `warn_s` before the 3 m conflict (`heard`: `lead_s` earlier, its
    "heard" timing), realistic vehicles (policy+filter), on `links` ("perfect", "degraded"), 5
    draws each. Module constants are read as the runs fly (monkeypatch first)."""
    import policy.eval as ev
    from bench.late_intruder import lead_s, scene
    from policy import evalsim
    from policy.pointmass import VehicleModel
    from policy.tracking import TrackingConfig

    model = VehicleModel.named("realistic")
    ctrl = ev.controllers(ev.EvalConfig(vehicles="realistic", controllers=("policy+filter",)))[
        "policy+filter"
    ]
    sim = evalsim.EvalSimConfig(vehicles=model, tracking=TrackingConfig.assumed(model, True))
    by_name = {"perfect": evalsim.PERFECT, "degraded": evalsim.DEGRADED}
    out = []
    for ratio in (1.5, 2.0):
        for name in links:
            lead = lead_s(by_name[name], sim.dt_s) if heard else 0.0
            starts, goals, nc, speeds = scene("overtake", ratio, warn_s + lead)
            for seed in range(5):
                ctrl.reset()
                rng = np.random.default_rng([35, seed])
                r = evalsim.run(
                    starts, goals, ctrl, by_name[name], sim, rng, nc, speeds, flying_start=True
                )
                out.append(float(r["intruder_min_sep"]))
    return out


def _share_of_the_escape_speed(off, along, closing, r, vmax, j_len):
    """`clear_speed` as it was (arrays or floats): capped at NC_CLEAR_SHARE of the escape speed,
    whatever that left along the track."""
    cap = NC_CLEAR_SHARE * np.minimum(2.0 * vmax, np.maximum(vmax, j_len))
    t = np.where((along > 0) & (closing > 1e-9), along / np.maximum(closing, 1e-9), np.inf)
    return np.maximum(NC_ESCAPE_SHARE * vmax, np.minimum((r - off) / np.maximum(t, 1e-9), cap))


def test_overtaken_3_s_after_it_is_heard_keeps_3_m(monkeypatch) -> None:
    """Heard 3 s before the 3 m conflict, both links: every run keeps 3 m on true positions;
    with the fixed share (before the clear speed) some did not (2.95-2.98 m)."""
    now = _overtakes(3.0, ("perfect", "degraded"))
    assert min(now) >= 3.0, now
    monkeypatch.setattr(traffic_rules, "clear_speed", lambda *a: NC_ESCAPE_SHARE * a[4])
    before = _overtakes(3.0, ("perfect", "degraded"))
    assert min(before) < 3.0, before


def test_overtaken_2_s_after_it_is_heard_keeps_3_m(monkeypatch) -> None:
    """Heard 2 s before, on the perfect link (heard the moment it appears) and on the 3 Hz link:
    every run keeps 3 m now that the escape keeps its speed along the intruder's track; capped
    at a share of the escape speed instead, the vehicle slowed along the track and some runs on
    the perfect link came to 2.98 m."""
    now = _overtakes(2.0, ("perfect",))
    assert min(now) >= 3.0, now
    # on the 3 Hz link, placed so that it is heard 2 s before (unless its first states are lost)
    late = _overtakes(2.0, ("degraded",), heard=True)
    assert min(late) >= 3.0, late
    monkeypatch.setattr(traffic_rules, "clear_speed", _share_of_the_escape_speed)
    before = _overtakes(2.0, ("perfect",))
    assert min(before) < 3.0, before
