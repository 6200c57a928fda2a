"""CPU of a flying agent's receive path per tick, in-process: what its tick's drain does with the
router's relay batches (comms/mesh.py `CellSubscription.drain`), without Zenoh and without the
rest of the tick, so that a change to it is measured apart from the noise of a whole agent.

    python -m bench.agent_receive [--neighbours 20] [--neighbour-hz 10] [--tick-hz 10,3.33,1]
    python -m bench.agent_receive --compare-tree /tmp/before   # that checkout's comms, then this

`--neighbours` signed vehicles 6-14 m around the agent, each stamping a state at
`--neighbour-hz` at a phase of its own and tagging it for the agent (trust/links.py), as flying
neighbours do; the relay puts each period's states into RelayBatch messages (comms/relay.py
`batches`) every 0.1 s; the agent drains whatever came every 1 / tick-hz (10 Hz: busy; 3.33:
calm; 1: holding at rest) through its own subscription's handler and gate (thinning at
`NeighbourConfig.verify_min_interval_s`, reach, link tags) into a NeighbourTable, on injected
time. Prints and returns, per tick: process CPU (us, best of `--repeats`), states drained,
states decoded and states that went on. With `--compare-tree`, the same bench runs on that
checkout's packages first (this file, run with that tree on PYTHONPATH), in one invocation.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RELAY_PERIOD_S = 0.1


def receive_cost(
    neighbours: int, neighbour_hz: float, tick_hz: float, seconds: float, repeats: int
) -> dict:
    """The receive path of one agent per tick (module docstring)."""
    import numpy as np

    from agent.neighbours import NeighbourConfig, NeighbourTable
    from bench.agent_profile import _Sample
    from comms import keys, relay
    from comms.gate import GateConfig
    from comms.mesh import Mesh
    from comms.schema import Mode, Role, VehicleState
    from comms.session import embedded_router, free_tcp_port
    from trust.auth import load_auth
    from trust.authority import throwaway_fleet

    me, others = 1, list(range(2, neighbours + 2))
    with tempfile.TemporaryDirectory() as d:
        fleet = throwaway_fleet(d, "rx", vehicles=[me, *others], stations=[1])
        signers = {v: load_auth(str(fleet.member_path(Role.VEHICLE, v))) for v in [me, *others]}
        t0_ns = 1_000_000_000_000
        period_ns = int(1e9 / neighbour_hz)
        # every state stamped, signed and tagged once; then put into the relay's batches
        stamped: list[tuple[int, bytes]] = []
        for k, vid in enumerate(others):
            ang = 2 * math.pi * k / len(others)
            r_m = 6.0 + 8.0 * (k % 5) / 4
            n_m, e_m = r_m * math.cos(ang), r_m * math.sin(ang)
            phase_ns = period_ns * k // len(others)
            for j in range(int(seconds * neighbour_hz)):
                stamp = t0_ns + phase_ns + j * period_ns
                st = VehicleState(
                    vid,
                    j + 1,
                    stamp,
                    (n_m + 0.1 * j, e_m, -6.0),
                    (1.0, 0.0, 0.0),
                    0.0,
                    Mode.GOTO,
                    True,
                )
                stamped.append((stamp, signers[vid].sign_state(st, [me]).encode()))
        stamped.sort()
        relay_ns = int(RELAY_PERIOD_S * 1e9)
        periods: dict[int, list[bytes]] = {}
        for stamp, payload in stamped:
            periods.setdefault((stamp - t0_ns) // relay_ns + 1, []).append(payload)
        block = (2, keys.cell_of((0.0, 0.0, -6.0)))
        key = "rx/relay/bench"
        batch_at = [
            (t0_ns + p * relay_ns, b) for p in sorted(periods) for b in relay.batches(periods[p], p)
        ]
        tick_ns = int(1e9 / tick_hz)
        ticks = [t0_ns + tick_ns * (i + 1) for i in range(int(seconds * tick_hz))]
        best = None
        for _ in range(repeats):
            with Mesh(embedded_router(free_tcp_port(), fleet="rx"), auth=signers[me]) as mesh:
                table = NeighbourTable(me, NeighbourConfig(), reach_m=40.0)
                table.snapshot(0.0, np.array([0.0, 0.0, -6.0]))  # where the agent is
                now = [t0_ns]
                mesh.clock_ns = lambda now=now: now[0]
                decoded = [0]
                went_on = [0]
                real = mesh._decode_state

                def counting(*a, real=real, decoded=decoded):
                    decoded[0] += 1
                    return real(*a)

                mesh._decode_state = counting

                def on_state(s, t, table=table, went_on=went_on):
                    went_on[0] += 1
                    table.update(s, t / 1e9)

                gate = GateConfig(min_interval_s=NeighbourConfig().verify_min_interval_s)
                if hasattr(mesh, "_admitters"):  # this tree: states heard, decoded when tried
                    admit = mesh._admitters(on_state, None, None, gate, me, table.worth_checking)[1]
                    hear = mesh._hear_relayed
                else:  # before comms/heard.py: every state decoded as drained
                    admit = mesh._admitter(  # type: ignore[attr-defined]
                        on_state, None, None, gate, me, table.worth_checking
                    )
                    hear = mesh._decode_relayed
                handler = mesh._state_batch_handler(admit, False, gate.batch_budget_s)
                drained, at, since = 0, 0, t0_ns
                c0 = time.process_time()
                for t in ticks:
                    now[0] = t
                    got = []
                    while at < len(batch_at) and batch_at[at][0] <= t:
                        got += hear(_Sample(key, batch_at[at][1]), block)
                        at += 1
                    drained += len(got)
                    if got:
                        handler(got, t, since)
                    since = t
                cpu_s = time.process_time() - c0
            row = {
                "neighbours": neighbours,
                "neighbour_hz": neighbour_hz,
                "tick_hz": tick_hz,
                "cpu_us_per_tick": cpu_s * 1e6 / len(ticks),
                "drained_per_tick": drained / len(ticks),
                "decoded_per_tick": decoded[0] / len(ticks),
                "went_on_per_tick": went_on[0] / len(ticks),
            }
            if best is None or row["cpu_us_per_tick"] < best["cpu_us_per_tick"]:
                best = row
        assert best is not None
        return best


def _say(rows: list[dict]) -> None:
    for row in rows:
        print(
            f"  tick {row['tick_hz']:g} Hz: {row['cpu_us_per_tick']:.0f} us CPU a tick, "
            f"{row['drained_per_tick']:.1f} states drained, {row['decoded_per_tick']:.1f} "
            f"decoded, {row['went_on_per_tick']:.1f} went on",
            flush=True,
        )


def run(args: argparse.Namespace) -> list[dict]:
    return [
        receive_cost(args.neighbours, args.neighbour_hz, hz, args.seconds, args.repeats)
        for hz in args.tick_hz
    ]


def other_tree(tree: Path, args: argparse.Namespace) -> list[dict]:
    """This bench's rows on `tree`'s packages: this file, copied out of bench/ (which would
    shadow the packages) and run with that tree on PYTHONPATH."""
    argv = [
        *("--neighbours", str(args.neighbours), "--neighbour-hz", str(args.neighbour_hz)),
        *("--tick-hz", ",".join(str(x) for x in args.tick_hz), "--seconds", str(args.seconds)),
        *("--repeats", str(args.repeats), "--json"),
    ]
    from bench import common

    return common.run_in_tree(tree, Path(__file__), argv)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--neighbours", type=int, default=20)
    ap.add_argument("--neighbour-hz", type=float, default=10.0)
    ap.add_argument(
        "--tick-hz",
        type=lambda s: [float(x) for x in s.split(",")],
        default=[10.0, 10.0 / 3, 1.0],
        help="the agent's tick rates to measure (comma list; default busy, calm, at rest)",
    )
    ap.add_argument("--seconds", type=float, default=20.0, help="injected time a measurement")
    ap.add_argument("--repeats", type=int, default=5, help="the best of this many")
    ap.add_argument(
        "--compare-tree",
        type=Path,
        default=None,
        metavar="PATH",
        help="another checkout (e.g. main before a change), measured first in the same run",
    )
    ap.add_argument(
        "--json", action="store_true", help="print this tree's rows as JSON only (no file)"
    )
    a = ap.parse_args()
    if a.json:
        print(json.dumps(run(a)))
        return
    from bench import common

    result: dict = {
        "what": "a flying agent's receive path per tick, in-process (bench/agent_receive.py)"
    }
    if a.compare_tree is not None:
        if not (a.compare_tree / "comms" / "mesh.py").exists():
            ap.error(f"--compare-tree {a.compare_tree}: no covey checkout there")
        print(f"{a.compare_tree}:", flush=True)
        before = other_tree(a.compare_tree, a)
        _say(before)
        result["before"] = {"tree": str(a.compare_tree.resolve()), "rows": before}
    print(f"{REPO} (this tree):", flush=True)
    rows = run(a)
    _say(rows)
    result["rows"] = rows
    print(common.write_json("agent_receive", result))


if __name__ == "__main__":
    main()
