"""bench/agent_floor.py: the in-process agent flies among its ring of neighbours (the C core
answering its filter calls), and `--compare-tree` runs a checkout's copy of the bench."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import agent_floor, common


def test_the_floor_agent_flies_its_goto_among_the_ring(monkeypatch) -> None:
    """The ring reaches the agent's table and its C filter; the agent keeps flying its goto
    (`_agent_ticks` raises if it left it)."""
    from agent import guidance_c

    seen: list[int] = []
    real = guidance_c.CCore.filter

    def counted(self, pos_m, vel_m_s, pref_m_s, nbr_pos_m, *a, **k):
        seen.append(len(nbr_pos_m))
        return real(self, pos_m, vel_m_s, pref_m_s, nbr_pos_m, *a, **k)

    monkeypatch.setattr(guidance_c.CCore, "filter", counted)
    cpu_ms = agent_floor._agent_ticks(20, 0.0, neighbours=6, c_core=True)
    assert cpu_ms > 0.0
    assert seen and max(seen) == 6, seen


def test_a_compared_tree_runs_its_own_copy_of_the_bench(tmp_path: Path) -> None:
    """`run_in_tree` on this checkout: the copied bench prints one JSON run of every
    measurement."""
    got = common.run_in_tree(
        common.REPO,
        Path(agent_floor.__file__),
        ["--ticks", "20", "--neighbours", "2", "--json"],
    )
    assert isinstance(got, dict)
    assert set(got) == {
        "tick_hot_ms",
        "tick_cold_ms",
        "wait_100ms_us",
        "ed25519_sign_us",
        "ed25519_verify_us",
    }
    assert all(v > 0 for v in got.values()), got


def test_medians_and_the_cold_ratio() -> None:
    runs = [
        {"tick_hot_ms": h, "tick_cold_ms": c, "wait_100ms_us": 1.0}
        for h, c in ((0.5, 1.0), (0.4, 1.2), (0.6, 0.9))
    ]
    med = agent_floor.medians(runs)
    assert med["tick_hot_ms"] == 0.5 and med["tick_cold_ms"] == 1.0
    assert med["cold_over_hot"] == pytest.approx(2.0)
