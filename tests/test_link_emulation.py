"""Link emulation: rates, loss models, latency bounds and spec parsing, on an injected clock."""

from __future__ import annotations

import random

import numpy as np
import pytest

from comms.link import (
    PROFILES,
    ChannelState,
    GilbertElliott,
    LinkEmulator,
    LinkProfile,
    LinkSpecError,
    decide,
    parse_link_spec,
    range_loss,
)
from comms.schema import VehicleState

SENDER_HZ = 10.0


def _state(vid: int, seq: int, stamp_ns: int, pos=(0.0, 0.0, -5.0)) -> VehicleState:
    return VehicleState(vid, seq, stamp_ns, pos, (0.0, 0.0, 0.0), 0.0)


def _run(profile: LinkProfile, duration_s: float, senders=(1,), seed=1, hz=SENDER_HZ, pos=None):
    """Offer `hz` states per sender for `duration_s` of injected time; deliver everything."""
    link = LinkEmulator(profile, np.random.default_rng(seed), clock_ns=lambda: 0, receiver_pos=pos)
    got: list[tuple[VehicleState, int]] = []
    period_ns = round(1e9 / hz)
    for k in range(int(duration_s * hz)):
        now = k * period_ns
        link.drain(now)
        for vid in senders:
            link.offer(_state(vid, k, now), now, lambda s, t: got.append((s, t)))
    link.drain(2**62)
    return link, got


def test_xbee_delivers_3_hz_with_20_percent_loss():
    duration_s = 600.0
    link, got = _run(PROFILES["xbee"], duration_s, senders=(1, 2))
    for vid, s in link.stats().items():
        assert s.offered == duration_s * SENDER_HZ
        tx_hz = s.transmitted / duration_s
        assert tx_hz == pytest.approx(3.0, rel=0.10), f"vehicle {vid} transmitted {tx_hz} Hz"
        assert s.loss_fraction == pytest.approx(0.20, abs=0.05)
        assert s.delivered / duration_s == pytest.approx(3.0 * 0.8, rel=0.10)
        assert s.dropped["rate"] + s.dropped["loss"] + s.delivered == s.offered
    assert len(got) == sum(s.delivered for s in link.stats().values())


def test_rate_gate_never_passes_two_states_in_one_slot():
    link, got = _run(LinkProfile(rate_hz=3.0), 60.0)
    stamps = [s.stamp_ns for s, _ in got]
    slots = [t // round(1e9 / 3) for t in stamps]
    assert len(slots) == len(set(slots))
    assert len(got) == pytest.approx(180, abs=2)


def test_rate_above_input_rate_passes_everything():
    link, got = _run(LinkProfile(rate_hz=20.0), 30.0)
    assert len(got) == 300


def test_gilbert_elliott_mean_loss_is_stationary_value():
    ge = GilbertElliott(p_good_bad=0.05, p_bad_good=0.3, loss_good=0.02, loss_bad=0.9)
    expected = (0.3 * 0.02 + 0.05 * 0.9) / 0.35
    assert ge.mean_loss == pytest.approx(expected)
    link, got = _run(LinkProfile(ge=ge), 3000.0)
    s = link.stats()[1]
    assert s.loss_fraction == pytest.approx(expected, abs=0.02)


def test_gilbert_elliott_losses_come_in_bursts():
    ge = GilbertElliott(p_good_bad=0.02, p_bad_good=0.2)
    link, got = _run(LinkProfile(ge=ge), 2000.0)
    delivered = np.zeros(20000, dtype=bool)
    delivered[[s.seq for s, _ in got]] = True
    lost = ~delivered
    # P(lost | previous lost) is 1 - p_bad_good = 0.8 for bursts, vs the mean loss ~0.09.
    p_follow = np.mean(lost[1:][lost[:-1]])
    assert p_follow == pytest.approx(0.8, abs=0.05)
    assert lost.mean() == pytest.approx(ge.mean_loss, abs=0.02)


def test_latency_and_jitter_bounds():
    profile = LinkProfile(latency_s=0.1, jitter_s=0.03)
    link, got = _run(profile, 100.0)
    delays_s = np.array([(t - s.stamp_ns) / 1e9 for s, t in got])
    assert len(got) == 1000
    assert delays_s.min() >= 0.07 - 1e-9 and delays_s.max() <= 0.13 + 1e-9
    assert delays_s.mean() == pytest.approx(0.1, abs=0.005)
    assert delays_s.std() > 0.01  # jitter is there
    seqs = [s.seq for s, _ in got]
    assert seqs == sorted(seqs)  # in order per sender
    s = link.stats()[1]
    assert s.max_delay_s <= 0.13 + 1e-9 and s.mean_age_s == pytest.approx(0.1, abs=0.005)


def test_delayed_states_wait_for_their_time():
    link = LinkEmulator(LinkProfile(latency_s=0.5), random.Random(0), clock_ns=lambda: 0)
    got = []
    link.offer(_state(1, 0, 0), 0, lambda s, t: got.append(t))
    assert link.drain(400_000_000) == 0 and got == []
    assert link.pending() == 1
    assert link.drain(500_000_000) == 1 and got == [500_000_000]


def test_scheduler_thread_delivers_and_stops():
    import threading
    import time

    done = threading.Event()
    with LinkEmulator(LinkProfile(latency_s=0.02), random.Random(0)) as link:
        now = time.time_ns()
        link.offer(_state(1, 0, now), now, lambda s, t: done.set())
        assert done.wait(5.0)
    assert link._thread is None


def test_range_loss_grows_with_distance():
    p = LinkProfile(range_m=50.0, falloff_m=50.0)
    assert range_loss(p, 10.0) == 0.0
    assert range_loss(p, 75.0) == pytest.approx(0.5)
    assert range_loss(p, 500.0) == 1.0
    assert range_loss(LinkProfile(range_m=50.0), 51.0) == 1.0
    near, _ = _run(p, 100.0, pos=lambda: (10.0, 0.0, -5.0))
    far, _ = _run(p, 100.0, pos=lambda: (75.0, 0.0, -5.0))
    assert near.stats()[1].delivered == 1000
    assert far.stats()[1].dropped["range"] == pytest.approx(500, abs=60)
    unknown, _ = _run(p, 10.0, pos=lambda: None)
    assert unknown.stats()[1].delivered == 100


def test_decide_is_pure():
    p = PROFILES["xbee"]
    c0 = ChannelState()
    a = decide(p, c0, 10, 0.5, 0.5, 0.5, 0.5)
    assert a == decide(p, c0, 10, 0.5, 0.5, 0.5, 0.5)
    assert c0 == ChannelState()
    assert decide(p, c0, 10, 0.1, 0.5, 0.5, 0.5)[0].reason == "loss"


def test_stats_text_fits_an_event():
    link, _ = _run(PROFILES["xbee"], 10.0, senders=tuple(range(1, 40)))
    text = link.stats_text()
    assert text.startswith("link xbee 1:") and len(text.encode()) <= 120


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("xbee", PROFILES["xbee"]),
        ("perfect", LinkProfile(name="perfect")),
        (
            "rate=3,loss=0.2,latency=0.1,jitter=0.03",
            LinkProfile(
                name="rate=3,loss=0.2,latency=0.1,jitter=0.03",
                rate_hz=3,
                loss=0.2,
                latency_s=0.1,
                jitter_s=0.03,
            ),
        ),
    ],
)
def test_parse_specs(spec, expected):
    assert parse_link_spec(spec) == expected


def test_parse_overrides_and_ge():
    p = parse_link_spec("xbee,ge=0.05:0.3")
    assert p.rate_hz == 3.0 and p.loss == 0.0 and p.ge == GilbertElliott(0.05, 0.3)
    p = parse_link_spec("wifi, loss=0.5, range=100:20")
    assert p.loss == 0.5 and p.range_m == 100 and p.falloff_m == 20 and p.latency_s == 0.01
    assert parse_link_spec("ge=0.1:0.2:0.01:0.8").ge.loss_bad == 0.8


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("", "empty --link spec"),
        ("lora", "unknown link profile 'lora'"),
        ("rate=fast", "'fast' is not a number"),
        ("loss=1.5", "must be a probability"),
        ("latency=-1", "must be a finite number >= 0"),
        ("speed=3", "unknown key 'speed'"),
        ("rate=3,rate=4", "rate= given twice"),
        ("loss=0.1,ge=0.1:0.2", "not both"),
        ("ge=0.1", "needs 2 or 4 numbers"),
        ("ge=0:0", "cannot both be 0"),
        ("rate", "unknown link profile 'rate'"),
        ("xbee,loss", "must look like key=value"),
        ("jitter=nan", "must be finite"),
        ("range=1:2:3", "needs 1 or 2 numbers"),
    ],
)
def test_bad_specs_say_why(spec, message):
    with pytest.raises(LinkSpecError, match=message.replace("(", r"\(")):
        parse_link_spec(spec)


def test_own_states_pass_through_uncounted():
    link = LinkEmulator(PROFILES["xbee"], random.Random(0), clock_ns=lambda: 0, own_id=7)
    got = []
    for k in range(10):
        link.offer(_state(7, k, k), k, lambda s, t: got.append(s.seq))
    assert got == list(range(10)) and link.stats() == {}
