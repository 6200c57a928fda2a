"""`covey bench`: section discovery, the summary, and a smoke run of the smallest section."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from bench import report
from bench.__main__ import OWN_ORDER, discover, inspect

REPO = Path(__file__).resolve().parent.parent


def test_discovery_finds_own_sections_first_and_reads_conventions(tmp_path: Path) -> None:
    names = [s.name for s in discover()]
    assert names[: len(OWN_ORDER)] == list(OWN_ORDER)
    conv = tmp_path / "conv.py"
    conv.write_text("def main(quick: bool = False) -> dict:\n    return {}\n")
    script = tmp_path / "script.py"
    script.write_text(
        'import argparse\ndef main(argv=None):\n    pass\nif __name__ == "__main__":\n    main()\n'
    )
    c, s = inspect(conv), inspect(script)
    assert c.convention and c.how(True) == "main(quick=True)"
    assert not s.convention and s.script and s.how(False) == "python -m bench.script"
    assert s.how(True).startswith("skipped")


def test_summary_renders_other_sections_generically(tmp_path: Path) -> None:
    (tmp_path / "other.json").write_text(
        json.dumps({"rows": [{"n": 2, "ms": 1.5}], "median": {"rate": 1234.5}})
    )
    text = report.write_summary(tmp_path).read_text()
    assert "## other" in text and "| n | ms |" in text and "median.rate = 1,234" in text


@pytest.mark.slow
def test_quick_inference_section_writes_json_and_summary(tmp_path: Path) -> None:
    out = tmp_path / "results"
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "--quick", "--only", "inference", "--out", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=280,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "[1/1] inference" in proc.stderr  # progress names the running section
    d = json.loads((out / "inference.json").read_text())
    assert (
        d["quick"] is True
        and d["machine"]["cores"] >= 1
        and len(d["machine"]["loadavg_1_5_15"]) == 3
    )
    assert d["peak"]["best_flop_s"] > 0
    assert [r["vehicles"] for r in d["single"]] == [2, 5, 10, 20, 35, 100]
    for r in d["single"]:
        assert r["paper_flops"] == (r["vehicles"] - 1) * 34_902 + 17_160
        assert r["numpy_median_us"] > 0 and r["numpy_share_of_peak"] > 0
    b = d["batch"]
    assert b["vehicles"] == 1000 and b["numpy_command_batch_ms"] > 0 and b["numpy_network_ms"] > 0
    assert "torch_network_ms" in b or b["torch"] == "not installed"
    assert (out / "inference.png").stat().st_size > 0
    summary = (out / "SUMMARY.md").read_text()
    assert "## Policy inference" in summary and "paper FLOPs" in summary
    run = json.loads((out / "run.json").read_text())
    assert run["sections"][0]["status"] == "ok" and not math.isnan(run["wall_s"])


def test_start_routers_moves_a_router_whose_port_was_taken(monkeypatch) -> None:
    """bench.common.start_routers: real `covey router` processes in a full mesh; the first
    port offered is already taken (as by another process's outgoing connection), so that
    router exits before READY and starts again on a new port."""
    import socket

    from bench import common
    from comms import session

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    offers = [taken.getsockname()[1]]
    real = session.free_tcp_port
    monkeypatch.setattr(session, "free_tcp_port", lambda *a: offers.pop() if offers else real())
    with taken, common.children() as kids:
        started = common.start_routers(kids, 2)
        ports = [port for _, port in started]
        assert len(ports) == 2 and taken.getsockname()[1] not in ports
        started[1][0].wait_for("covey router: 1 router(s)", timeout_s=60)


@pytest.mark.parametrize("n", [100, 300, 1000, 1234])
def test_scale_layout_sites_are_areas_of_adjacent_blocks(n: int) -> None:
    """bench.scale.layout: every vehicle once, blocks of equal size (+-1) that do not overlap,
    each block beside the next (snake order), and 3 sites of consecutive blocks (so each site
    is an area of adjacent blocks)."""
    from bench.scale import MIN_HOSTS, ROUTERS, layout

    blocks = layout(n)
    assert len(blocks) >= MIN_HOSTS
    ids = [i for b in blocks for i in range(b.first_id, b.first_id + b.vehicles)]
    assert ids == list(range(1, n + 1))
    assert max(b.vehicles for b in blocks) - min(b.vehicles for b in blocks) <= 1
    corners = [b.start_ne_m for b in blocks]
    assert len(set(corners)) == len(corners)
    steps = [math.dist(c, d) for c, d in itertools.pairwise(corners)]
    assert max(steps) == pytest.approx(min(steps))  # the next block is beside this one
    sites = [b.site for b in blocks]
    assert sites == sorted(sites) and set(sites) == set(range(ROUTERS))


def test_scale_site_latencies_split_by_the_senders_site() -> None:
    from bench.scale import Block, site_latencies_ms

    blocks = [Block(1, 2, (0.0, 0.0), 0), Block(3, 2, (40.0, 0.0), 1)]
    rows = [
        {"latency_ms": [1.0, 2.0, float("nan")], "latency_senders": [2, 3, 4]},
        {"latency_ms": [4.0, 8.0], "latency_senders": [1, 4]},
    ]
    same, cross = site_latencies_ms(blocks, rows)
    assert sorted(same) == [1.0, 8.0] and sorted(cross) == [2.0, 4.0]


def test_scale_spread_reports_each_run_the_median_and_how_many_met_the_targets() -> None:
    """bench.scale.spread: the repeated largest size, against issue 15's targets."""
    from bench.scale import spread

    def run(p99_ms: float, ack_ms: float, ups: float) -> dict:
        return {
            "latency_ms_p99": p99_ms,
            "takeoff_ack_ms_p99": ack_ms,
            "station": {"updates_per_s": ups},
            "load_avg_1min_at_start": 1.0,
        }

    got = spread([run(11.0, 500.0, 10.0), run(25.0, 1200.0, 9.96), run(19.0, 900.0, 9.8)])
    assert got["runs"] == 3
    assert got["latency_ms_p99"]["values"] == [11.0, 25.0, 19.0]
    assert got["latency_ms_p99"]["median"] == 19.0
    assert got["latency_ms_p99"]["met_in"] == 2
    assert got["takeoff_ack_ms_p99"]["met_in"] == 2
    assert got["station_updates_per_s"]["met_in"] == 2  # 9.96 prints as 10.0; 9.8 does not


def test_scale_bench_refuses_fewer_than_one_repeat() -> None:
    from bench.scale import main

    with pytest.raises(ValueError, match="repeats must be >= 1"):
        main(quick=True, repeats=0)


def test_crossings_bench_smoke(tmp_path: Path, monkeypatch) -> None:
    """bench/crossings.py flies its quick grid: no pair below 3 m, and the asymmetric 60-degree
    crossing is where the sparse rule beats the policy's early turn."""
    from bench import common, crossings

    monkeypatch.setenv(common.OUT_ENV, str(tmp_path))
    res = crossings.main(quick=True)
    assert (tmp_path / "crossings.png").is_file()
    s = res["summary"]
    assert s["cases"] == 4 and all(s[c]["collisions"] == 0 for c in crossings.CONTROLLERS)
    assert min(s[c]["min_sep_m"] for c in crossings.CONTROLLERS) >= 3.0
    row = next(r for r in res["rows"] if r["angle_deg"] == 60 and r["offset_m"] == 1.0)
    assert row["rule_extra_time"] < row["policy_extra_time"] - 0.01


def test_call_patterns_bench_smoke(tmp_path: Path, monkeypatch) -> None:
    """bench/call_patterns.py flies the public runtime's calling patterns on its quick cases:
    no pair below 3 m for the policy, every policy pattern arrives, ORCA deadlocks the circle
    of 8, and holding `preferred` beats holding the already-filtered `command` there."""
    from bench import call_patterns, common

    monkeypatch.setenv(common.OUT_ENV, str(tmp_path))
    res = call_patterns.main(quick=True, links=("perfect",))
    assert (tmp_path / "call_patterns.png").is_file()
    s = res["links"]["perfect"]["summary"]
    for suite in ("conflict", "circle"):
        for p in call_patterns.PATTERNS[:3]:
            m = s[suite][p]
            assert m["collisions"] == 0 and m["min_sep_m"] >= 3.0
            assert m["succeeded"] == m["cases"]
    assert s["circle"]["orca"]["succeeded"] < s["circle"]["orca"]["cases"]
    circle8 = next(r for r in res["links"]["perfect"]["rows"] if r["case"] == "circle-8")
    assert circle8["hold_preferred_extra_time"] < circle8["hold_command_extra_time"] - 0.05
    assert len(res["table"]) == 2 * len(call_patterns.PATTERNS)  # 2 suites, 1 link
    with pytest.raises(ValueError, match="pattern must be one of"):
        call_patterns.PublicCaller(None, "sometimes")
    with pytest.raises(ValueError, match="links must be some of"):
        call_patterns.main(quick=True, links=("lossy",))


@pytest.mark.slow
def test_crowd_sigma_bench_smoke(tmp_path: Path, monkeypatch) -> None:
    """bench/crowd_sigma.py flies its quick circle at k 3 and 4 with realistic vehicles and the
    ideal baseline: every k has its cases and a ratio to ideal above 1 (the berth costs time),
    the larger k keeps at least as much between estimates, and the plot is written."""
    from bench import common, crowd_sigma

    monkeypatch.setenv(common.OUT_ENV, str(tmp_path))
    res = crowd_sigma.main(quick=True)
    assert (tmp_path / "crowd_sigma.png").is_file()
    assert json.loads((tmp_path / "crowd_sigma.json").read_text())["sigma_ks"] == [3.0, 4.0]
    s3, s4 = res["summary"]["3.0"], res["summary"]["4.0"]
    assert s3["cases"] == s4["cases"] == 4  # circle of 16, 2 seeds, 2 links
    assert [r["sigma_k"] for r in res["by_k"]] == [3.0, 4.0]
    assert s3["median_over_ideal"] > 1.0 and s4["median_over_ideal"] > 1.0
    assert s4["median_closest_estimated_m"] >= s3["median_closest_estimated_m"] - 0.05
    assert all(r["vehicles"] == "ideal" for r in res["runs"][:4])
    for s in (s3, s4):  # the 9 m gap, 2 seeds, both links
        assert s["gap"]["runs"] == 4 and s["gap"]["closest_to_a_zone_m"] > 0.0
    # --only-gap re-flies the gap at one k and keeps the circles and the other k's gap runs
    again = crowd_sigma.regap((4.0,))
    assert again["runs"] == res["runs"] and again["summary"]["3.0"] == s3
    assert sorted(r["sigma_k"] for r in again["gap_runs"]) == [3.0] * 4 + [4.0] * 4
    assert again["summary"]["4.0"]["gap"]["runs"] == 4
