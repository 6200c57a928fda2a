"""Where one flying keyed agent's CPU goes: py-spy on the real process (a profiling aid, not a
`covey bench` section; py-spy is not a project dependency: `pip install py-spy` first).

    python -m bench.agent_profile [--neighbours 20] [--neighbour-hz 10] [--out /tmp/agent.txt]

bench/agent_cpu.py's real `covey agent` (sim backend, keyed: every neighbour state signed and
verified) flies a goto with `--neighbours` signed neighbours 6-14 m around it, each publishing at
`--neighbour-hz` (10: all manoeuvring; 3: the steady rate of vehicles flying straight or
hovering, comms/state_rate.py); py-spy samples
it (all threads, native frames off, idle frames dropped) over the flying window and writes the
raw folded stacks; this module prints the CPU per tick and the top frames by own and by
cumulative samples.
"""

from __future__ import annotations

import argparse
import collections
import math
import os
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from bench import agent_cpu, common


def top(folded: str, n: int) -> tuple[int, list[tuple[str, int]], list[tuple[str, int]]]:
    """(total samples, top `n` frames by own samples, top `n` by cumulative samples)."""
    own: collections.Counter[str] = collections.Counter()
    cum: collections.Counter[str] = collections.Counter()
    total = 0
    for line in folded.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack:
            continue
        k = int(count)
        total += k
        frames = stack.split(";")
        own[frames[-1]] += k
        for f in set(frames[1:]):  # the first frame is the thread
            cum[f] += k
    return total, own.most_common(n), cum.most_common(n)


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds so far of each thread of `pid`, summed by thread name (/proc/<pid>/task)."""
    out: collections.Counter[str] = collections.Counter()
    tck = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the thread ended
        out[re.sub(r"[-_]?\d+$", "", name)] += (int(fields[11]) + int(fields[12])) / tck
    return dict(out)


class _Sample:
    """What Mesh's state handler reads of a zenoh.Sample: its payload's bytes and its key."""

    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = self
        self._bytes = payload

    def to_bytes(self) -> bytes:
        return self._bytes


def receive_cost(
    vehicles: int, spacing_m: float, state_hz: float, reach: bool, seconds: float = 5.0
) -> dict:
    """CPU of the receive path of the vehicle at the middle of `covey demo`'s grid, hovering,
    per second of (injected) time: every other vehicle's signed state at `state_hz`, through the
    agent's own handler (Mesh's decode, key and cell checks, the keyed gate with its thinning,
    and, with `reach`, the reach check) into its NeighbourTable. In-process and without Zenoh,
    so the machine's other load does not change what is done, only how fast (process CPU time).
    Zenoh's own per-message work and the tick are not in it (bench.flying_agents has them)."""
    import numpy as np

    from agent.guidance import GuidanceConfig
    from agent.neighbours import NeighbourConfig, NeighbourTable
    from comms import keys
    from comms.gate import GateConfig
    from comms.mesh import Mesh
    from comms.schema import Mode, Role, VehicleState
    from comms.scope import ScopeConfig
    from comms.session import embedded_router, free_tcp_port
    from groundstation.demo import grid_starts
    from trust.auth import load_auth
    from trust.authority import throwaway_fleet

    starts = grid_starts(vehicles, spacing_m)
    me = int(np.argmin([math.hypot(n, e) for n, e in starts])) + 1
    reach_m = GuidanceConfig().scope(ScopeConfig()).reach_m
    with tempfile.TemporaryDirectory() as d:
        fleet = throwaway_fleet(d, "rx", vehicles=range(1, vehicles + 1), stations=[1])
        signers = {
            v: load_auth(str(fleet.member_path(Role.VEHICLE, v))) for v in fleet_ids(vehicles)
        }
        t0_ns = time.time_ns()
        samples = []
        for k in range(int(seconds * state_hz)):
            stamp = t0_ns + int(k * 1e9 / state_hz)
            for vid, (n, e) in enumerate(starts, start=1):
                if vid == me:
                    continue
                st = VehicleState(
                    vid, k + 1, stamp, (n, e, -6.0), (0.0, 0.0, 0.0), 0.0, Mode.HOLDING, True
                )
                signed = signers[vid].sign_state(st)
                samples.append(
                    (stamp, keys.state("rx", vid, keys.cell_of(st.pos_ned_m)), signed.encode())
                )
        with Mesh(embedded_router(free_tcp_port(), fleet="rx"), auth=signers[me]) as mesh:
            table = (
                NeighbourTable(me, NeighbourConfig(), reach_m=reach_m)
                if reach
                else NeighbourTable(me)
            )
            table.snapshot(0.0, np.array([*starts[me - 1], -6.0]))
            extra = {"worth_checking": table.worth_checking} if reach else {}
            now = [0]
            mesh.clock_ns = lambda: now[0]
            handler = mesh._state_handler(
                mesh._admitters(
                    lambda s, t: table.update(s, t / 1e9),
                    None,
                    None,
                    GateConfig(min_interval_s=NeighbourConfig().verify_min_interval_s),
                    me,
                    **extra,
                )[0]
            )
            c0 = time.process_time()
            for stamp, key, payload in samples:
                now[0] = stamp + 5_000_000
                handler(_Sample(key, payload))
            cpu_s = time.process_time() - c0
            gate = mesh.gates[-1]
    return {
        "vehicles": vehicles,
        "state_hz": state_hz,
        "reach_m": reach_m if reach else None,
        "states_in_per_s": len(samples) / seconds,
        "verified_per_s": gate.accepted / seconds,
        "in_table": len(table.latest()),
        "cpu_ms_per_s": cpu_s * 1e3 / seconds,
    }


def fleet_ids(vehicles: int) -> range:
    return range(1, vehicles + 1)


def keyed_flight(
    neighbours: int,
    neighbour_hz: float,
    link_tags: bool = True,
    while_flying=None,
    spread: bool = True,
    agent_args: tuple[str, ...] = (),
) -> dict:
    """bench/agent_cpu.py's flight in a throwaway keyed fleet of the agent and its neighbours;
    `link_tags` False: nobody tags (a tree from before the tags runs with the default).
    `spread`: each neighbour publishes at a phase of its own, as separate vehicles do (False:
    all at once, as before round nine); `agent_args`: more `covey agent` flags."""
    from trust.authority import throwaway_fleet

    with tempfile.TemporaryDirectory() as d:
        ids = [agent_cpu.AGENT_ID, *agent_cpu.neighbour_ids(neighbours)]
        throwaway_fleet(d, agent_cpu.FLEET, vehicles=ids, stations=[1])
        kw = {} if link_tags else {"link_tags": False}
        return agent_cpu.agent_flight(
            False,
            keys_dir=d,
            neighbours=neighbours,
            neighbour_hz=neighbour_hz,
            while_flying=while_flying,
            spread=spread,
            agent_args=agent_args,
            **kw,
        )


def cpu_only(
    neighbours: int,
    neighbour_hz: float,
    link_tags: bool = True,
    spread: bool = True,
    agent_args: tuple[str, ...] = (),
) -> dict:
    """The same flight without the profiler (py-spy costs CPU and perturbs what it samples):
    the agent's CPU per tick and its state rate."""
    f = keyed_flight(neighbours, neighbour_hz, link_tags, None, spread, agent_args)["flying"]
    print(
        f"keyed agent, {neighbours} neighbours at {neighbour_hz:g} Hz "
        f"({'each at its own phase' if spread else 'all at once'}), link tags "
        f"{'on' if link_tags else 'off'}, {' '.join(agent_args) or 'as shipped'}, flying, no "
        f"profiler: {f['cpu_ms_per_tick']:.2f} ms CPU per 100 ms, states "
        f"{f['states'] / f['window_s']:.1f} Hz",
        flush=True,
    )
    return f


def compare(neighbours: int, neighbour_hz: float, spread: bool, args: str, repeats: int) -> None:
    """`cpu_only` as shipped and with the agent flags `args`, alternating, `repeats` each:
    the medians and their ratio (one machine, one run)."""
    other = tuple(args.split())
    got: dict[tuple[str, ...], list[float]] = {(): [], other: []}
    for _ in range(repeats):
        for agent_args in ((), other):
            f = cpu_only(neighbours, neighbour_hz, True, spread, agent_args)
            got[agent_args].append(f["cpu_ms_per_tick"])
    shipped, alt = (statistics.median(got[k]) for k in ((), other))
    print(
        f"median of {repeats}: as shipped {shipped:.2f} ms, with {args} {alt:.2f} ms per 100 ms "
        f"(shipped / other {shipped / alt:.2f})"
    )


def main(
    neighbours: int,
    neighbour_hz: float,
    out: str,
    rate_hz: int = 200,
    link_tags: bool = True,
    spread: bool = True,
) -> None:

    folded = out + ".folded"
    by_thread: dict[str, float] = {}

    def spy(pid: int, seconds: float) -> None:
        by_thread.update(py_spy(pid, seconds, folded, rate_hz))

    r = keyed_flight(neighbours, neighbour_hz, link_tags, while_flying=spy, spread=spread)
    f = r["flying"]
    head = (
        f"keyed agent, {neighbours} neighbours at {neighbour_hz:g} Hz, link tags "
        f"{'on' if link_tags else 'off'}, flying: {f['cpu_ms_per_tick']:.2f} ms CPU per tick "
        f"({100 * f['cpu_share_of_one_core']:.1f} % of a core)"
    )
    lines = profile_lines(head, folded, by_thread, rate_hz)
    Path(out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def py_spy(pid: int, seconds: float, folded: str, rate_hz: int = 200) -> dict[str, float]:
    """py-spy on the process `pid` for `seconds` (all threads, idle frames dropped, raw folded
    stacks written to `folded`); returns each thread name's CPU ms per 10 Hz tick over the
    window, from /proc."""
    pyspy = shutil.which("py-spy") or str(common.REPO / ".venv/bin/py-spy")
    t0 = thread_cpu_s(pid)
    subprocess.run(
        [pyspy, "record", "--pid", str(pid), "--duration", str(int(seconds))]
        + ["--rate", str(rate_hz), "--format", "raw", "--threads", "--output", folded]
        + ["--nonblocking"],
        check=False,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    t1 = thread_cpu_s(pid)
    ticks = seconds * agent_cpu.TICK_HZ
    return {k: (v - t0.get(k, 0.0)) * 1e3 / ticks for k, v in t1.items()}


def profile_lines(head: str, folded: str, by_thread: dict[str, float], rate_hz: int) -> list[str]:
    """A profile as text: `head`, the CPU per tick by thread, the top frames by own and by
    cumulative samples."""
    total, own, cum = top(Path(folded).read_text(), 40)
    return [
        f"{head}, {total} samples at {rate_hz} Hz",
        "CPU ms per tick by thread name (/proc, over py-spy's window):",
        *(f"  {ms:6.3f}  {name}" for name, ms in sorted(by_thread.items(), key=lambda kv: -kv[1])),
        "own samples (tottime):",
        *(f"  {100 * k / max(total, 1):5.1f} %  {name}" for name, k in own),
        "cumulative samples:",
        *(f"  {100 * k / max(total, 1):5.1f} %  {name}" for name, k in cum),
    ]


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--neighbours", type=int, default=20)
    ap.add_argument("--neighbour-hz", type=float, default=10.0)
    ap.add_argument("--out", default="/tmp/agent_profile.txt")
    ap.add_argument(
        "--cpu-only", action="store_true", help="no profiler: only the agent's CPU per tick"
    )
    ap.add_argument(
        "--no-link-tags",
        action="store_true",
        help="nobody tags states (trust/links.py): the agent verifies every signature",
    )
    ap.add_argument(
        "--burst",
        action="store_true",
        help="the neighbours publish all at once each period (before round nine: each at a "
        "phase of its own, as separate vehicles do)",
    )
    ap.add_argument(
        "--compare-args",
        default=None,
        metavar="FLAGS",
        help="with --cpu-only: alternate the agent as shipped and with these flags "
        "(e.g. '--zenoh-default-pools'), --repeats each",
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rate-hz", type=int, default=200, help="py-spy's samples a second")
    ap.add_argument(
        "--receive-model",
        default=None,
        metavar="N",
        type=int,
        help="instead: receive_cost() of the middle vehicle of an N-vehicle demo grid, "
        "10 Hz without the reach check (before) and 3 Hz with it (after)",
    )
    a = ap.parse_args()
    if a.receive_model:
        import json

        for hz, reach in ((10.0, False), (3.0, False), (3.0, True)):
            print(json.dumps(receive_cost(a.receive_model, 8.0, hz, reach)))
    elif a.cpu_only and a.compare_args:
        compare(a.neighbours, a.neighbour_hz, not a.burst, a.compare_args, a.repeats)
    elif a.cpu_only:
        cpu_only(a.neighbours, a.neighbour_hz, not a.no_link_tags, not a.burst)
    else:
        main(
            a.neighbours,
            a.neighbour_hz,
            a.out,
            a.rate_hz,
            link_tags=not a.no_link_tags,
            spread=not a.burst,
        )
