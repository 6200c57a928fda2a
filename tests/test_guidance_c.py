"""One vehicle's guidance through the C core (agent/guidance_c.py) against numpy's, the
reference: the same held decisions and filtered velocities, tick by tick, on random scenes with
the real sky's inputs (uncertainties, traffic that does not cooperate, manned aircraft), and
numpy wherever the core does not cover a call."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews


def _views(rng, k: int, own_id: int = 1, sky: bool = True) -> NeighbourViews:
    ang = rng.uniform(0, 2 * np.pi, k)
    r = rng.uniform(3.5, 14.0, k)
    pos = np.zeros((1, k, 3))
    pos[0, :, 0], pos[0, :, 1], pos[0, :, 2] = r * np.cos(ang), r * np.sin(ang), -10.0
    vel = np.zeros((1, k, 3))
    vel[0, :, :2] = rng.normal(0.0, 0.7, (k, 2))
    coop = rng.random((1, k)) > 0.2
    return NeighbourViews(
        pos,
        vel,
        rng.uniform(-np.pi, np.pi, (1, k)),
        np.ones((1, k), bool),
        np.zeros((1, k), bool),
        np.arange(2, 2 + k, dtype=np.int64).reshape(1, k),
        np.array([own_id], np.int64),
        rng.uniform(0.0, 0.6, (1, k)) if sky else None,
        coop if sky else None,
        np.array([0.5]) if sky else None,
        (~coop & (rng.random((1, k)) > 0.5)) if sky else None,
    )


def _fly(guidance: BatchGuidance, rng_seed: int, k: int, ticks: int = 12, sky: bool = True):
    """(ticks, 3) velocities and (ticks,) filtered flags of one vehicle flying a goto past `k`
    random neighbours (a new scene each tick, one clock: decisions at the policy's period)."""
    rng = np.random.default_rng(rng_seed)
    rows = np.zeros(1, int)
    pos, vel = np.array([[0.0, 0.0, -10.0]]), np.array([[0.8, 0.2, 0.0]])
    goal = np.array([[60.0, 10.0, -10.0]])
    out, filtered, decided = [], [], []
    for t in range(ticks):
        step = guidance.step(
            0.1 * t,
            rows,
            pos,
            vel,
            np.array([0.2]),
            goal,
            np.array([False]),
            _views(rng, k, sky=sky),
        )
        out.append(step.vel_ned_m_s[0])
        filtered.append(bool(step.filtered[0]))
        decided.append(bool(step.decided[0]))
    return np.array(out), np.array(filtered), np.array(decided)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("k", [1, 3, 12, 30])
def test_the_c_core_flies_as_numpy_does(seed: int, k: int) -> None:
    numpy_g = BatchGuidance(GuidanceConfig(), 1)
    c_g = BatchGuidance(GuidanceConfig(c_core=True), 1, numpy_g.policy)
    assert c_g.c_core is not None and numpy_g.c_core is None
    want, want_f, want_d = _fly(numpy_g, seed, k)
    got, got_f, got_d = _fly(c_g, seed, k)
    np.testing.assert_allclose(got, want, atol=2e-4)
    assert (got_d == want_d).all() and got_d.sum() >= 2
    assert c_g.c_core.calls["filter"] == 12 and c_g.c_core.calls["decide"] == got_d.sum()
    assert c_g.c_core.calls["numpy"] == 0
    if k >= 12:  # crowded: the filter had work to do, and the flags agree where it did
        assert want_f.any()
    assert (got_f == want_f)[np.abs(got - want).max(axis=1) < 1e-6].all()


def test_exact_neighbours_and_other_settings_fly_alike() -> None:
    cfg = dict(separation_m=4.0, cruise_speed_m_s=1.5, sparse_rule=False)
    numpy_g = BatchGuidance(GuidanceConfig(**cfg), 1)
    c_g = BatchGuidance(GuidanceConfig(c_core=True, **cfg), 1, numpy_g.policy)
    want, _, _ = _fly(numpy_g, 7, 8, sky=False)
    got, _, _ = _fly(c_g, 7, 8, sky=False)
    np.testing.assert_allclose(got, want, atol=2e-4)


def test_numpy_answers_what_the_core_does_not_cover() -> None:
    """More neighbours than the core's network sees (numpy sees them all), and zones: numpy
    decides and filters, and the result is numpy's own."""
    numpy_g = BatchGuidance(GuidanceConfig(), 1)
    c_g = BatchGuidance(GuidanceConfig(c_core=True), 1, numpy_g.policy)
    want, _, _ = _fly(numpy_g, 3, 50, ticks=3)
    got, _, _ = _fly(c_g, 3, 50, ticks=3)
    assert c_g.c_core.calls["decide"] == 0 and c_g.c_core.calls["numpy"] >= 1
    np.testing.assert_allclose(got, want, atol=2e-4)

    square = np.array([[20.0, -5.0], [30.0, -5.0], [30.0, 5.0], [20.0, 5.0]])
    for g in (numpy_g, c_g):
        g.set_zones([square])
    filtered_before = c_g.c_core.calls["filter"]
    want, _, _ = _fly(numpy_g, 4, 6, ticks=4)
    got, _, _ = _fly(c_g, 4, 6, ticks=4)
    assert c_g.c_core.calls["filter"] == filtered_before
    np.testing.assert_allclose(got, want, atol=2e-4)


def test_without_a_compiler_the_agent_says_so_and_flies_numpy(monkeypatch, caplog) -> None:
    from agent import guidance_c

    monkeypatch.setenv("CC", "no-such-compiler-here")
    with caplog.at_level(logging.WARNING, logger="agent.guidance_c"):
        g = BatchGuidance(GuidanceConfig(c_core=True), 1)
        assert not guidance_c.build()  # what covey demo asks before it starts its agents
    assert g.c_core is None
    assert "C guidance core is not available" in caplog.text and "no-such-compiler" in caplog.text
    assert "--no-c-core" in caplog.text
    got, _, _ = _fly(g, 1, 5, ticks=3)
    assert np.isfinite(got).all()


def test_many_rows_stay_on_numpy_batches() -> None:
    assert BatchGuidance(GuidanceConfig(c_core=True), 3).c_core is None


def test_covey_agent_flies_the_c_core_unless_told_not_to() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    assert not GuidanceConfig().c_core  # library callers and evaluations: numpy, the reference
    assert agent_cli.config_from_args(p.parse_args(["--id", "3"])).guidance.c_core
    off = agent_cli.config_from_args(p.parse_args(["--id", "3", "--no-c-core"]))
    assert not off.guidance.c_core


def test_beyond_the_cores_range_numpy_answers_and_it_is_said_once(caplog) -> None:
    """200 km from the fleet origin (the C core takes 100 km; the wire 1,000 km): every call
    goes to numpy, which answers as it always does, and the log says so once per kind."""
    numpy_g = BatchGuidance(GuidanceConfig(), 1)
    c_g = BatchGuidance(GuidanceConfig(c_core=True), 1, numpy_g.policy)
    far = np.array([2e5, 0.0, 0.0])

    def fly(g):
        rng = np.random.default_rng(4)
        rows, out = np.zeros(1, int), []
        for t in range(6):
            v = _views(rng, 5, sky=False)
            v.pos_m[...] += far
            step = g.step(
                0.1 * t,
                rows,
                np.array([[2e5, 0.0, -10.0]]),
                np.array([[0.8, 0.2, 0.0]]),
                np.array([0.2]),
                np.array([[2e5 + 60.0, 10.0, -10.0]]),
                np.array([False]),
                v,
            )
            out.append(step.vel_ned_m_s[0])
        return np.array(out)

    want = fly(numpy_g)
    with caplog.at_level(logging.WARNING, logger="agent.guidance_c"):
        got = fly(c_g)
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert c_g.c_core.calls["decide"] == c_g.c_core.calls["filter"] == 0
    assert c_g.c_core.calls["numpy"] >= 7
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and all("numpy answers it" in m for m in said), said
