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
import os
import re
import shutil
import subprocess
import tempfile
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


def main(neighbours: int, neighbour_hz: float, out: str, rate_hz: int = 200) -> None:
    from comms.authority import throwaway_fleet

    pyspy = shutil.which("py-spy") or str(common.REPO / ".venv/bin/py-spy")
    folded = out + ".folded"

    by_thread: dict[str, float] = {}

    def spy(pid: int, seconds: float) -> None:
        t0 = thread_cpu_s(pid)
        subprocess.run(
            [
                pyspy,
                "record",
                "--pid",
                str(pid),
                "--duration",
                str(int(seconds)),
                "--rate",
                str(rate_hz),
                "--format",
                "raw",
                "--threads",
                "--output",
                folded,
                "--nonblocking",
            ],
            check=False,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        t1 = thread_cpu_s(pid)
        ticks = seconds * agent_cpu.TICK_HZ
        by_thread.update({k: (v - t0.get(k, 0.0)) * 1e3 / ticks for k, v in t1.items()})

    with tempfile.TemporaryDirectory() as d:
        ids = [agent_cpu.AGENT_ID, *agent_cpu.neighbour_ids(neighbours)]
        throwaway_fleet(d, agent_cpu.FLEET, vehicles=ids, stations=[1])
        r = agent_cpu.agent_flight(
            False, keys_dir=d, neighbours=neighbours, neighbour_hz=neighbour_hz, while_flying=spy
        )
    f = r["flying"]
    total, own, cum = top(Path(folded).read_text(), 40)
    lines = [
        f"keyed agent, {neighbours} neighbours at {neighbour_hz:g} Hz, flying: {f['cpu_ms_per_tick']:.2f} ms CPU per tick "
        f"({100 * f['cpu_share_of_one_core']:.1f} % of a core), {total} samples at {rate_hz} Hz",
        "CPU ms per tick by thread name (/proc, over py-spy's window):",
        *(f"  {ms:6.3f}  {name}" for name, ms in sorted(by_thread.items(), key=lambda kv: -kv[1])),
        "own samples (tottime):",
        *(f"  {100 * k / total:5.1f} %  {name}" for name, k in own),
        "cumulative samples:",
        *(f"  {100 * k / total:5.1f} %  {name}" for name, k in cum),
    ]
    Path(out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--neighbours", type=int, default=20)
    ap.add_argument("--neighbour-hz", type=float, default=10.0)
    ap.add_argument("--out", default="/tmp/agent_profile.txt")
    a = ap.parse_args()
    main(a.neighbours, a.neighbour_hz, a.out)
