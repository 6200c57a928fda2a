"""Cortex-M7 cost of the C policy: instructions per evaluation vs vehicle count, flash, RAM.

    python -m bench.firmware_cortexm      # prints a table, writes bench/results/firmware_cortexm.{json,png}

The core is cross-compiled (arm-none-eabi-gcc -mcpu=cortex-m7 -mfpu=fpv5-d16
-mfloat-abi=hard -O2) and run under qemu-system-arm -M mps2-an500 -icount shift=0.
QEMU has no DWT cycle counter, so instructions are counted: under -icount shift=0 each
instruction advances virtual time by 1 ns and SysTick ticks every 40 ns (checked by a
calibration loop in the image). CPU load assumes one cycle per instruction (CPI = 1);
a real M7 runs such code at roughly CPI 0.7-1.5 (dual issue vs flash wait states), so
the loads are estimates within that factor.

N is the number of vehicles in the scene, as in the paper: the LSTM runs N - 1 steps.
"hold+filter" is what the PX4 module runs (covey_guidance_step): one decision per trained
period (1 s) with the sparse rule (covey_sparse_choose as measured plus one full filter call:
an upper bound, its own filter call may or may not have run on the bench scene), and the
separation filter at every 10 Hz tick, all N - 1 neighbours closing in.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from firmware import cases, cortexm, hostbuild

RESULTS = Path(__file__).resolve().parent / "results"
N_VEHICLES = (2, 5, 10, 20, 35)
CLOCKS_HZ = {"pixhawk4_216MHz": 216e6, "pixhawk6_480MHz": 480e6}
RATES_HZ = {"10Hz": 10.0, "3Hz_radio": 3.0, "1Hz_train_step": 1.0}
"""The paper gives no guidance rate: 10 Hz is ours, 3 Hz its radio rate, 1 Hz its training step."""
PAPER_LOAD = 0.04
TICK_HZ = 10.0
"""Guidance tick rate of the PX4 module (CVY_RATE_HZ): the filter runs every tick."""
DECISION_HZ = 1.0
"""Decisions per second at the trained period (1 s at 3 m and 1 m/s)."""


def measure(npz: Path, build_dir: Path) -> dict:
    """Sizes and instruction counts of one weights file."""
    elfs = cortexm.build([], npz_path=npz, build_dir=build_dir)
    run = cortexm.run_qemu(elfs["cases"])
    return {
        "footprint": cortexm.sizes(elfs["footprint"]),
        "core_object": cortexm.sizes(elfs["core"]),
        "max_stack_frame_b": cortexm.max_stack_bytes(build_dir),
        "instructions_per_tick": 1.0 / run.ticks_per_instruction,
        "instructions": {k: run.instructions(k) for k in sorted(run.bench_ticks)},
        "filter_instructions": {k: run.filter_instructions(k) for k in sorted(run.filter_ticks)},
        "sparse_instructions": {k: run.sparse_instructions(k) for k in sorted(run.sparse_ticks)},
    }


def table(m: dict, hidden: int, x: int) -> list[dict]:
    rows = []
    for n in N_VEHICLES:
        instr = m["instructions"][n - 1]
        flops = cortexm.paper_flops(n, hidden=hidden, x=x)
        row = {
            "vehicles": n,
            "neighbours": n - 1,
            "instructions": instr,
            "paper_flops": flops,
            "instructions_per_flop": instr / flops,
        }
        f_instr = m["filter_instructions"][n - 1]
        row["filter_instructions"] = f_instr
        s_instr = m["sparse_instructions"][n - 1]
        row["sparse_instructions"] = s_instr
        # what the module runs: decide (policy + sparse rule) at the trained period, filter
        # every 10 Hz tick
        row["guidance_instructions_per_s"] = (
            DECISION_HZ * (instr + s_instr + f_instr) + TICK_HZ * f_instr
        )
        for cname, hz in CLOCKS_HZ.items():
            row[f"load_{cname}_hold_filter"] = row["guidance_instructions_per_s"] / hz
            row[f"ms_at_{cname}"] = 1e3 * instr / hz
            for rname, rate in RATES_HZ.items():
                row[f"load_{cname}_{rname}"] = instr * rate / hz
            row[f"max_rate_hz_within_4pct_{cname}"] = PAPER_LOAD * hz / instr
        rows.append(row)
    return rows


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name, m in results["configs"].items():
        ks = np.array(sorted(m["instructions"]))
        ax.plot(ks + 1, [m["instructions"][k] / 1e6 for k in ks], "o-", label=f"C on M7 ({name})")
    n = np.arange(1, 42)
    ax.plot(n, [cortexm.paper_flops(int(v)) / 1e6 for v in n], "k--", label="paper FLOPs formula")
    ax.set_xlabel("vehicles N (LSTM steps = N - 1)")
    ax.set_ylabel("millions per evaluation")
    ax.set_title("Cortex-M7 instructions per policy evaluation (QEMU -icount)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS / "firmware_cortexm.json")
    args = parser.parse_args(argv)
    if cortexm.missing_tools():
        print(f"missing tools: {', '.join(cortexm.missing_tools())}", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        # the paper's network (encoding "paper": x = 3) with random weights, and the shipped one
        paper_npz = cases.write_random_npz(Path(tmp) / "paper.npz", encoding="paper")
        cfg_shipped = json.loads(str(np.load(hostbuild.SHIPPED_NPZ)["config"]))
        configs = {
            "paper h=63 x=3": (paper_npz, 63, 3),
            f"shipped h={cfg_shipped['hidden']} x={cfg_shipped['input']}": (
                hostbuild.SHIPPED_NPZ,
                int(cfg_shipped["hidden"]),
                int(cfg_shipped["input"]),
            ),
        }
        results = {
            "method": "qemu-system-arm -M mps2-an500 -icount shift=0, SysTick ticks x 40",
            "cpi_assumed": 1.0,
            "configs": {},
            "tables": {},
        }
        for name, (npz, hidden, x) in configs.items():
            m = measure(npz, Path(tmp) / name.replace(" ", "_").replace("=", ""))
            ks = np.array(sorted(m["instructions"]))
            slope, icept = np.polyfit(ks, [m["instructions"][k] for k in ks], 1)
            m["fit_instructions_per_neighbour"] = slope
            m["fit_instructions_fixed"] = icept
            results["configs"][name] = m
            results["tables"][name] = table(m, hidden, x)

    for name, m in results["configs"].items():
        fp = m["footprint"]
        print(f"\n== {name}")
        print(
            f"flash {fp['flash'] / 1024:.1f} KiB (core object {m['core_object']['flash'] / 1024:.1f}"
            f" KiB), RAM {fp['ram'] / 1024:.1f} KiB static + {m['max_stack_frame_b']} B deepest "
            f"frame; {m['instructions_per_tick']:.2f} instructions per SysTick tick"
        )
        print(
            f"fit: {m['fit_instructions_per_neighbour']:,.0f} instructions per neighbour + "
            f"{m['fit_instructions_fixed']:,.0f} (paper: 34,902 FLOPs per neighbour + 17,160)"
        )
        print(
            " N  instr      paperFLOPs instr/FLOP  ms@216  %216@10Hz %216@3Hz  ms@480  %480@10Hz"
            "  Hz@4%(216)  filter  sparse  %216 hold+filter"
        )
        for r in results["tables"][name]:
            print(
                f"{r['vehicles']:2d} {r['instructions']:10,.0f} {r['paper_flops']:10,d} "
                f"{r['instructions_per_flop']:8.2f} {r['ms_at_pixhawk4_216MHz']:7.2f} "
                f"{100 * r['load_pixhawk4_216MHz_10Hz']:8.2f} "
                f"{100 * r['load_pixhawk4_216MHz_3Hz_radio']:8.2f} "
                f"{r['ms_at_pixhawk6_480MHz']:7.2f} {100 * r['load_pixhawk6_480MHz_10Hz']:8.2f} "
                f"{r['max_rate_hz_within_4pct_pixhawk4_216MHz']:10.1f} "
                f"{r['filter_instructions']:7,.0f} {r['sparse_instructions']:7,.0f} "
                f"{100 * r['load_pixhawk4_216MHz_hold_filter']:8.2f}"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2, default=float) + "\n")
    plot(results, args.out.with_suffix(".png"))
    print(f"\nwrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
