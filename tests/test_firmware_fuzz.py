"""The C policy core under AddressSanitizer + UBSan, fed valid and hostile inputs.

Every mutated case (NaN, inf, huge, negative counts, future or ancient stamps...)
must come back with exactly the fault that firmware.cases.expected_status predicts,
and no input may crash the core or trip a sanitizer. Valid cases must give the same
bits as the optimised build.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from firmware import cases, hostbuild

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")

N_VALID = 300
N_MUTATED = 20_000
N_ACTION = 3_000
ACTION_BAD = (float("nan"), float("inf"), float("-inf"), 2.0e9, -3.0e38, 1.0e9, 0.5)


def _sanitized_driver():
    try:
        return hostbuild.build_driver(hostbuild.header_for(hostbuild.SHIPPED_NPZ), sanitize=True)
    except RuntimeError as e:
        if "sanitize" in str(e) or "asan" in str(e).lower():
            pytest.skip(f"the C compiler cannot build with sanitizers: {str(e)[-300:]}")
        raise


def _command_cases(rng):
    valid = [cases.random_case(rng) for _ in range(N_VALID)]
    mutated = []
    for k in range(N_MUTATED):
        # mostly small cases keep the sanitized run short; every 50th is full size
        base = cases.random_case(rng, n_nbrs=None if k % 50 == 0 else int(rng.integers(0, 6)))
        mutated.append(cases.mutate(base, rng))
    return valid, mutated


def _action_cases(rng):
    """(driver line, expected status) for covey_action with hostile sequences."""
    out = []
    for _ in range(N_ACTION):
        n = int(rng.choice([-5, -1, 0, 1, 3, 17, 40, 41, 1000, 2**31 - 1]))
        n_vals = max(0, min(n, cases.MAX_NEIGHBOURS)) * 5 + 2
        values = rng.normal(size=n_vals).astype(np.float32)
        for _ in range(int(rng.integers(0, 3))):
            values[int(rng.integers(0, n_vals))] = rng.choice(ACTION_BAD)
        if not 0 <= n <= cases.MAX_NEIGHBOURS:
            expect = cases.STATUS["range"]
        elif not np.all(np.isfinite(values)):
            expect = cases.STATUS["nonfinite"]
        elif np.any(np.abs(values) > cases.MAX_ABS_FEATURE):
            expect = cases.STATUS["range"]
        else:
            expect = cases.STATUS["ok"]
        seq = values[:-2].reshape(-1, 5)
        out.append((cases.action_line(seq, values[-2:], n_steps=n), expect))
    return out


def test_fuzz_under_sanitizers(capsys):
    asan = _sanitized_driver()
    plain = hostbuild.build_driver(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    rng = np.random.default_rng(6)
    valid, mutated = _command_cases(rng)
    actions = _action_cases(rng)
    all_cases = valid + mutated
    text = "\n".join([*map(cases.case_line, all_cases), *(a for a, _ in actions)]) + "\n"

    lines, stderr = hostbuild.run_driver(asan, text)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr[-2000:]
    assert len(lines) == len(all_cases) + len(actions)

    # valid inputs: OK, and bit-identical to the -O2 build
    plain_lines, _ = hostbuild.run_driver(plain, text)
    assert plain_lines == lines

    counts = {name: 0 for name in cases.STATUS}
    for c, line in zip(all_cases, lines, strict=False):
        out = cases.parse_command_output(line)
        expect = cases.expected_status(c)
        assert out["status"] == expect, (line, c)
        counts[next(k for k, v in cases.STATUS.items() if v == expect)] += 1
        assert np.all(np.isfinite(out["vel"])) and np.all(np.isfinite(out["action"]))
        if expect == cases.STATUS["ok"]:
            assert np.hypot(*out["action"]) <= 1.0 + 1e-6
            assert np.hypot(*out["vel"]) <= float(np.float32(c.cruise_m_s)) * (1.0 + 1e-6)
        else:
            assert not np.any(out["vel"]), "a fault must command zero velocity"
    for (_, expect), line in zip(actions, lines[len(all_cases) :], strict=True):
        assert int(line.split()[0]) == expect, line
    assert counts["ok"] >= N_VALID and counts["nonfinite"] > 100 and counts["range"] > 100
    assert counts["stale"] > 10
    with capsys.disabled():
        print(
            f"\n[firmware fuzz] {len(all_cases)} command inputs ({len(mutated)} mutated) + "
            f"{len(actions)} network inputs under ASan+UBSan: statuses {counts}, clean"
        )
