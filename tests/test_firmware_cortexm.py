"""The policy core cross-compiled for a Cortex-M7 and run under QEMU (mps2-an500).

Its outputs on shared cases must equal the host build's and the numpy runtime's
within 1e-5 (the libm differs: newlib on the target, glibc on the host). The image
also counts instructions per evaluation (qemu -icount); the counts are checked for
sanity and linearity only, never against a time.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from firmware import cases, cortexm, hostbuild

pytestmark = [
    pytest.mark.skipif(
        bool(cortexm.missing_tools()),
        reason="needs the Debian packages gcc-arm-none-eabi libnewlib-arm-none-eabi "
        f"qemu-system-arm (missing: {', '.join(cortexm.missing_tools())})",
    ),
    pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)"),
]

TOL = 1e-5
N_CASES = 60
PIXHAWK4_FLASH_B = 2 * 1024 * 1024
PIXHAWK4_RAM_B = 512 * 1024


@pytest.fixture(scope="module")
def target_run(tmp_path_factory):
    rng = np.random.default_rng(11)
    case_list = [
        cases.random_case(rng, n_nbrs=n % (cases.MAX_NEIGHBOURS + 1))
        for n in range(0, 7 * N_CASES, 7)
    ]
    build_dir = tmp_path_factory.mktemp("cortexm")
    elfs = cortexm.build(case_list, build_dir=build_dir)
    return case_list, elfs, cortexm.run_qemu(elfs["cases"]), build_dir


def test_target_equals_host_and_runtime(target_run, capsys):
    case_list, _, run, _ = target_run
    driver = hostbuild.build_driver(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    lines, _ = hostbuild.run_driver(driver, "\n".join(map(cases.case_line, case_list)) + "\n")
    assert len(run.results) == len(case_list) == len(lines)
    err_host = err_runtime = 0.0
    identical = 0
    for c, line, r in zip(case_list, lines, run.results, strict=True):
        host = cases.parse_command_output(line)
        status, vel_n, vel_e, a_f, a_r, n_used = r
        assert status == host["status"] == cases.STATUS["ok"]
        assert n_used == host["n_used"]
        target = np.array([vel_n, vel_e, a_f, a_r])
        host_v = np.concatenate([host["vel"], host["action"]])
        identical += int(np.array_equal(target, host_v))
        err_host = max(err_host, float(np.abs(target - host_v).max()) / max(c.cruise_m_s, 1.0))
        vel, action, _ = cases.runtime_reference(hostbuild.SHIPPED_NPZ, c)
        err_runtime = max(
            err_runtime,
            float(np.abs(target[2:] - action).max()),
            float(np.abs(target[:2] - vel).max()) / c.cruise_m_s,
        )
    with capsys.disabled():
        print(
            f"\n[firmware cortex-m7] {len(case_list)} cases: max err vs host {err_host:.3g} "
            f"({identical} bit-identical), vs numpy runtime {err_runtime:.3g}"
        )
    assert err_host <= TOL
    assert err_runtime <= TOL


def test_instruction_counts_are_linear_in_neighbours(target_run):
    _, _, run, _ = target_run
    # qemu -icount shift=0: 1 instruction = 1 ns; SysTick at 25 MHz = 40 ns a tick
    assert 1.0 / run.ticks_per_instruction == pytest.approx(40.0, rel=1e-3)
    ks = np.array(sorted(run.bench_ticks))
    instr = np.array([run.instructions(k) for k in ks])
    assert np.all(np.diff(instr) > 0)
    slope, icept = np.polyfit(ks, instr, 1)
    resid = instr - (slope * ks + icept)
    assert np.abs(resid).max() < 0.01 * instr.max()  # linear in N, as the paper says
    # one LSTM step is 4H(H + X) = 17,136 multiply-adds plus 5H activations
    assert 20_000 < slope < 400_000


def test_footprint_fits_a_pixhawk(target_run):
    _, elfs, _, build_dir = target_run
    size = cortexm.sizes(elfs["footprint"])
    assert size["flash"] < PIXHAWK4_FLASH_B
    assert size["ram"] < PIXHAWK4_RAM_B
    assert 0 < cortexm.max_stack_bytes(build_dir) < 4096
