"""SUMMARY.md from the JSON files in the results folder (the README quotes it).

Own sections get tables with their anchors (paper FLOPs, CPU peak, raw Zenoh); any other
section's JSON is rendered generically: tables for lists of records, key = value otherwise.
"""

from __future__ import annotations

import json
from pathlib import Path

OWN = ("inference", "training", "mesh", "agent_cpu")


def _f(x, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool) or not isinstance(x, int | float):
        return str(x)
    if x != x:  # NaN
        return "-"
    if isinstance(x, int) or abs(x) >= 1000:
        return f"{x:,.0f}"
    return f"{x:.{digits}g}"


def _table(head: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(_f(c) for c in r) + " |" for r in rows]
    return out + [""]


def _load(out: Path, name: str) -> dict | None:
    p = out / f"{name}.json"
    return json.loads(p.read_text()) if p.is_file() else None


def _stamp(d: dict) -> str:
    m = d.get("machine", {})
    q = " (quick)" if d.get("quick") else ""
    return f"_{m.get('utc', '?')}{q}, load average {m.get('loadavg_1_5_15', '?')}_"


def inference(d: dict) -> list[str]:
    pk = d["peak"]["best_flop_s"]
    lines = [
        "## Policy inference",
        _stamp(d),
        "",
        f"CPU peak (float32 {d['peak']['matmul_n']}^3 matmul, one thread, best of runs): **{pk / 1e9:.1f} GFLOP/s** "
        f"(median {d['peak']['median_flop_s'] / 1e9:.1f}). Paper FLOPs = (N-1) x 34,902 + 17,160.",
        "",
    ]
    rows = [
        [
            r["vehicles"],
            r["paper_flops"],
            r["paper_flops_at_peak_us"],
            r["numpy_median_us"],
            r["numpy_min_us"],
            100 * r["numpy_share_of_peak"],
            r.get("c_median_us"),
            r.get("c_min_us"),
            100 * r["c_share_of_peak"] if "c_share_of_peak" in r else None,
        ]
        for r in d["single"]
    ]
    lines += _table(
        [
            "N vehicles",
            "paper FLOPs",
            "us at CPU peak",
            "numpy us median",
            "numpy us min",
            "numpy % of peak",
            "C us median",
            "C us min",
            "C % of peak",
        ],
        rows,
    )
    lines += [
        "One vehicle: `GuidancePolicy.actor.action` (features + network, no safety filter) and `CPolicy.action` (C core via ctypes; "
        "at most 64 reports, so no N = 100). % of peak = the shipped network's FLOPs / median time / CPU peak.",
        "",
    ]
    b = d["batch"]
    lines += [
        f"Batched, {b['vehicles']} vehicles, nearest {b['nearest']} ({_f(b['paper_flops'])} paper FLOPs):",
        "",
    ]
    rows = [
        [
            "numpy command_batch (features + network)",
            b["numpy_command_batch_ms"],
            b["per_vehicle_us"],
            None,
        ],
        [
            "numpy command_batch + safety filter",
            b["numpy_command_batch_ms_filter"],
            1e3 * b["numpy_command_batch_ms_filter"] / b["vehicles"],
            None,
        ],
        [
            "numpy network only",
            b["numpy_network_ms"],
            1e3 * b["numpy_network_ms"] / b["vehicles"],
            100 * b["numpy_network_share_of_peak"],
        ],
    ]
    if "torch_network_ms" in b:
        rows.append(
            [
                f"torch {b['torch']} network only, 1 thread",
                b["torch_network_ms"],
                1e3 * b["torch_network_ms"] / b["vehicles"],
                100 * b["torch_network_share_of_peak"],
            ]
        )
    else:
        rows.append([f"torch: {b.get('torch', 'skipped')}", None, None, None])
    return lines + _table(["path", "ms per batch", "us per vehicle", "% of CPU peak"], rows)


def training(d: dict) -> list[str]:
    e, p, s = d["env"], d["ppo"], d["shipped"]
    lines = ["## Training", _stamp(d), ""]
    rows = [
        [
            "vectorized env (random actions)",
            f"{_f(e['arena_steps_s'])} arena-steps/s, {_f(e['vehicle_steps_s'])} vehicle-steps/s",
        ]
    ]
    if "samples_s" in p:
        rows.append(
            [
                f"PPO trainer ({p['preset']}, {p['num_envs']} arenas x {p['num_steps']} steps, {p['torch_threads']} torch thread)",
                f"{_f(p['samples_s'])} samples/s, {_f(p['episodes_s'])} episodes/s ({p['updates']} updates, {_f(p['wall_s'])} s)",
            ]
        )
    else:
        rows.append(["PPO trainer", p.get("skipped", "-")])
    shipped = f"{_f(s.get('trained_episodes'))} episodes (last stage)"
    if "log_wall_s" in s:
        where = (
            ""
            if s.get("log_in_git")
            else " (the run directories named in policy/weights/README.md, joined; not in git)"
        )
        same = (
            ""
            if s.get("log_matches_weights")
            else " - its last row does not match the shipped episode count"
        )
        shipped += (
            f"; log {s['log']}{where}: {_f(s['log_wall_s'] / 60)} min wall in total, 95 % of the final success "
            f"({_f(s['final_success'])}) after {_f(s['wall_s_to_95pct_of_final_success'] / 60)} min "
            f"({_f(s['episodes_to_95pct_of_final_success'])} episodes), 95 % of the final reward ({_f(s['final_reward'])}) "
            f"after {_f(s['wall_s_to_95pct_of_final_reward'] / 60)} min ({_f(s['episodes_to_95pct_of_final_reward'])} episodes){same}"
        )
    elif "estimated_wall_s" in s:
        shipped += f"; about {_f(s['estimated_wall_s'] / 60)} min at the PPO rate above ({s['estimate_note']})"
    rows.append([f"shipped policy ({s['weights']})", shipped])
    lines += _table(["what", "measured"], rows)
    lines += [f"- {ln}" for ln in s.get("readme_lines", [])]
    return lines + ([""] if s.get("readme_lines") else [])


def mesh(d: dict) -> list[str]:
    r = d["ratios"]
    lines = [
        "## Mesh (loopback, one hub + two publisher processes)",
        _stamp(d),
        "",
        f"States at {d['rate_hz']:g} Hz per vehicle, {d['state_bytes']} B each; latency = receive time in the hub's callback minus the sender's stamp.",
        "",
    ]
    rows = [
        [
            x["kind"],
            x["vehicles"],
            x.get("latency_ms_p50"),
            x.get("latency_ms_p99"),
            x.get("delivered_share"),
            r.get(
                f"state_p50_{x['kind']}_over_raw_n{x['vehicles']}",
                1.0 if x["kind"] == "raw" else None,
            ),
            x.get("hub_cpu_us_per_state"),
        ]
        for x in d["states"]
    ]
    lines += _table(
        [
            "publisher",
            "vehicles",
            "p50 ms",
            "p99 ms",
            "delivered share",
            "p50 / raw Zenoh",
            "receiver CPU us per state",
        ],
        rows,
    )
    lines += ["Broadcast command (one query to `v/*/cmd`) until every vehicle's ack is in:", ""]
    rows = [
        [
            x["kind"],
            x["vehicles"],
            x.get("all_acks_ms_p50"),
            x.get("all_acks_ms_p99"),
            x.get("incomplete"),
            r.get(
                f"command_p50_{x['kind']}_over_raw_n{x['vehicles']}",
                1.0 if x["kind"] == "raw" else None,
            ),
        ]
        for x in d["commands"]
    ]
    return lines + _table(
        ["responder", "vehicles", "p50 ms", "p99 ms", "incomplete rounds", "p50 / raw Zenoh"], rows
    )


def agent_cpu(d: dict) -> list[str]:
    lines = [
        "## Agent process",
        _stamp(d),
        "",
        f"One `covey agent` (sim backend) at {d['tick_hz']:g} Hz with {d['neighbours']} neighbours publishing at 10 Hz; CPU from /proc over the window.",
        "",
    ]
    rows = [
        [
            phase,
            x["window_s"],
            100 * x["cpu_share_of_one_core"],
            x["cpu_ms_per_tick"],
            x["tick_jitter_ms_p50"],
            x["tick_jitter_ms_p99"],
        ]
        for phase, x in (
            ("landed (mesh + states only)", d["landed"]),
            ("flying a goto (policy + safety filter)", d["flying"]),
        )
    ]
    lines += _table(
        [
            "phase",
            "window s",
            "% of one core",
            "CPU ms per tick",
            "tick jitter p50 ms",
            "tick jitter p99 ms",
        ],
        rows,
    )
    fs = d.get("fleet_sim")
    if fs:
        lines += [
            f"`covey fleet-sim`, {fs['vehicles']} vehicles in one process, wall time of one tick (physics, mode events, "
            f"batched policy + safety filter, {fs['vehicles']} states published); the budget at 10 Hz is {_f(fs['budget_ms_at_10hz'])} ms:",
            "",
        ]
        lines += _table(
            ["landed ms", "holding ms", "goto ms p50", "goto ms p99", "vehicles in goto"],
            [
                [
                    fs["landed_tick_ms_p50"],
                    fs["holding_tick_ms_p50"],
                    fs["goto_tick_ms_p50"],
                    fs["goto_tick_ms_p99"],
                    fs["in_goto"],
                ]
            ],
        )
    return lines


def generic(name: str, d) -> list[str]:
    """Any other section's JSON: lists of records as tables, scalars as key = value."""
    lines = [f"## {name} (from its own script)", ""]
    scalars: list[str] = []

    def walk(prefix: str, v, depth: int) -> None:
        if isinstance(v, dict) and depth < 3:
            for k, x in v.items():
                walk(f"{prefix}.{k}" if prefix else str(k), x, depth + 1)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            cols = [c for c in v[0] if isinstance(v[0][c], int | float | str)][:9]
            lines.extend(
                [f"{prefix}:", ""] + _table(cols, [[x.get(c) for c in cols] for x in v[:15]])
            )
        elif isinstance(v, int | float | str | bool) and prefix not in ("section",):
            scalars.append(f"- {prefix} = {_f(v)}")

    walk(
        "",
        {k: v for k, v in d.items() if k != "machine"} if isinstance(d, dict) else {"value": d},
        0,
    )
    return lines + scalars[:40] + [""]


def headline(out: Path) -> list[str]:
    """A dozen numbers with their anchors, for the top of SUMMARY.md and docs/performance.md."""
    rows: list[list] = []
    inf, tr, me, ag = (_load(out, n) for n in OWN)
    if inf:
        pk = inf["peak"]["best_flop_s"]
        rows.append(
            ["CPU peak, float32, one core", f"{pk / 1e9:.1f} GFLOP/s", "best of 256^3 matmuls"]
        )
        for r in inf["single"]:
            if r["vehicles"] in (2, 20, 100):
                c = f", C {_f(r['c_median_us'])} us" if "c_median_us" in r else ""
                rows.append(
                    [
                        f"policy, one vehicle, N = {r['vehicles']}",
                        f"numpy {_f(r['numpy_median_us'])} us{c}",
                        f"paper {_f(r['paper_flops'])} FLOPs = {_f(r['paper_flops_at_peak_us'])} us at peak; numpy at {_f(100 * r['numpy_share_of_peak'])} % of peak",
                    ]
                )
        b = inf["batch"]
        t = (
            f", torch network {_f(b['torch_network_ms'])} ms ({_f(100 * b['torch_network_share_of_peak'])} % of peak)"
            if "torch_network_ms" in b
            else ""
        )
        rows.append(
            [
                f"policy, {b['vehicles']} vehicles batched, nearest {b['nearest']}",
                f"numpy {_f(b['numpy_command_batch_ms'])} ms ({_f(b['per_vehicle_us'])} us/vehicle)",
                f"network alone {_f(b['numpy_network_ms'])} ms = {_f(100 * b['numpy_network_share_of_peak'])} % of peak{t}",
            ]
        )
    if tr:
        rows.append(
            [
                "vectorized env",
                f"{_f(tr['env']['vehicle_steps_s'])} vehicle-steps/s",
                f"{_f(tr['env']['arena_steps_s'])} arena-steps/s",
            ]
        )
        p, s = tr["ppo"], tr["shipped"]
        if "samples_s" in p:
            rows.append(
                [
                    "PPO trainer",
                    f"{_f(p['samples_s'])} samples/s",
                    f"{_f(p['episodes_s'])} episodes/s, 1 torch thread",
                ]
            )
        if "log_wall_s" in s:
            rows.append(
                [
                    "shipped policy",
                    f"{_f(s['log_episodes'])} episodes in {_f(s['log_wall_s'] / 60)} min",
                    f"95 % of final reward after {_f(s['wall_s_to_95pct_of_final_reward'] / 60)} min; final success {_f(s['final_success'])}",
                ]
            )
    if me:
        by = {(x["kind"], x["vehicles"]): x for x in me["states"]}
        for n in (10, 100, 500):
            c, r = by.get(("covey", n)), by.get(("raw", n))
            if c and r:
                rows.append(
                    [
                        f"state latency, {n} vehicles at 10 Hz",
                        f"p50 {_f(c['latency_ms_p50'])} ms, p99 {_f(c['latency_ms_p99'])} ms",
                        f"raw Zenoh p50 {_f(r['latency_ms_p50'])} ms (x{_f(c['latency_ms_p50'] / r['latency_ms_p50'])}); delivered {_f(c['delivered_share'])} vs {_f(r['delivered_share'])}",
                    ]
                )
        cb = {(x["kind"], x["vehicles"]): x for x in me["commands"]}
        for n in (10, 50, 500):
            c, r = cb.get(("covey", n)), cb.get(("raw", n))
            if c and r:
                rows.append(
                    [
                        f"broadcast -> all acks, {n} vehicles",
                        f"p50 {_f(c['all_acks_ms_p50'])} ms",
                        f"raw Zenoh {_f(r['all_acks_ms_p50'])} ms (x{_f(c['all_acks_ms_p50'] / r['all_acks_ms_p50'])})",
                    ]
                )
    if ag:
        f = ag["flying"]
        rows.append(
            [
                f"agent process, 10 Hz, {ag['neighbours']} neighbours",
                f"{_f(100 * f['cpu_share_of_one_core'])} % of a core",
                f"{_f(f['cpu_ms_per_tick'])} ms CPU per tick; tick jitter p50 {_f(f['tick_jitter_ms_p50'])} ms, p99 {_f(f['tick_jitter_ms_p99'])} ms",
            ]
        )
        e = ag.get("flying_policy_every_tick")
        if e:
            rows.append(
                [
                    "agent process, policy every tick (old behaviour)",
                    f"{_f(100 * e['cpu_share_of_one_core'])} % of a core",
                    f"{_f(e['cpu_ms_per_tick'])} ms CPU per tick; as shipped the policy decides once per decision period",
                ]
            )
        fs = ag.get("fleet_sim")
        if fs:
            rows.append(
                [
                    f"fleet-sim tick, {fs['vehicles']} vehicles flying",
                    f"{_f(fs['goto_tick_ms_p50'])} ms",
                    f"budget {_f(fs['budget_ms_at_10hz'])} ms at 10 Hz; landed {_f(fs['landed_tick_ms_p50'])} ms",
                ]
            )
    return _table(["what", "measured (median)", "anchor / detail"], rows) if rows else []


def update_doc(doc: Path, lines: list[str], when: str) -> None:
    """Replace the block between the headline markers of `doc` (if it has them)."""
    start, end = "<!-- headline:start -->", "<!-- headline:end -->"
    if not doc.is_file():
        return
    text = doc.read_text()
    if start not in text or end not in text:
        return
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    block = "\n".join(
        [start, f"_From the run of {when}; regenerated by `covey bench`._", "", *lines, end]
    )
    doc.write_text(head + block + tail)


def write_summary(out: Path) -> Path:
    run = _load(out, "run") or {}
    m = run.get("machine", {})
    lines = [
        "# covey benchmarks",
        "",
        f"Machine: {m.get('cpu', '?')}, {m.get('cores', '?')} cores, shared (load average at the end of the run "
        f"{m.get('loadavg_1_5_15', '?')}). Medians unless marked; ratios are the point, absolute numbers move with the load.",
        f"Regenerate: `covey bench` (full, {_f(run.get('wall_s'))} s here{' - this was a --quick run' if run.get('quick') else ''}) "
        "or `covey bench --quick`; one section: `covey bench --only mesh`. Details: docs/performance.md.",
        "",
    ]
    lines += headline(out)
    if run.get("sections"):
        lines += _table(
            ["section", "how it ran", "status", "wall s"],
            [[r["section"], r["how"], r["status"], r["wall_s"]] for r in run["sections"]],
        )
    renderers = {"inference": inference, "training": training, "mesh": mesh, "agent_cpu": agent_cpu}
    for name, fn in renderers.items():
        d = _load(out, name)
        if d is not None:
            try:
                lines += fn(d)
            except (KeyError, TypeError, ZeroDivisionError) as exc:
                lines += [f"## {name}", "", f"(could not render {name}.json: {exc!r})", ""]
    for r in run.get("sections", []):
        if r.get("output_tail"):
            lines += [
                f"## {r['section']} (printed output; it writes no JSON)",
                "",
                "```",
                *r["output_tail"],
                "```",
                "",
            ]
    for p in sorted(out.glob("*.json")):
        if p.stem not in (*OWN, "run"):
            try:
                lines += generic(p.stem, json.loads(p.read_text()))
            except (ValueError, KeyError) as exc:
                lines += [f"## {p.stem}", "", f"(unreadable: {exc})", ""]
    path = out / "SUMMARY.md"
    path.write_text("\n".join(lines).rstrip() + "\n")
    from bench.common import DOCS, RESULTS

    if out.resolve() == RESULTS.resolve():
        update_doc(DOCS / "performance.md", headline(out), m.get("utc", "?"))
    return path


if __name__ == "__main__":
    import sys

    from bench.common import RESULTS

    print(write_summary(Path(sys.argv[1]) if len(sys.argv) > 1 else RESULTS))
