"""`covey eval --vehicles realistic` (smoke): circles and forced conflicts of the quick suite on
both links, policy+filter with realistic vehicles (lag, gusts, 0.5 m GNSS drift); collisions
and the closest approach are judged on TRUE positions: none with the filter's uncertainty
inflation; the estimates' closest approach is kept too."""

from __future__ import annotations

import pytest

from policy import eval as policy_eval


def _run(tmp_path, sigma_k: float | None):
    cfg = policy_eval.EvalConfig(
        out=str(tmp_path / f"k{sigma_k}"),
        quick=True,
        seed=3,
        suites=("circle", "conflict"),
        controllers=("policy+filter",),
        vehicles="realistic",
        sigma_k=sigma_k,
        figures=False,
        progress=False,
    )
    return policy_eval.main(cfg)


def test_realistic_eval_has_no_true_collisions(tmp_path, capsys):
    result = _run(tmp_path, None)
    runs = result["runs"]
    assert len(runs) == 8 and all(r["collisions"] == 0 for r in runs)
    assert all(r["success"] for r in runs)
    true_min = min(r["min_sep"] for r in runs)
    est_min = min(r["est_min_sep"] for r in runs)
    assert true_min >= 3.0 and est_min > 3.6
    assert result["config"]["vehicles"] == "realistic"
    assert {"est_min_sep", "collision_cases"} <= set(result["summary"][0])
    with capsys.disabled():
        print(f"\n[eval realistic, quick] closest true {true_min:.2f} m, estimates {est_min:.2f} m")


def test_vehicles_flag_is_checked(capsys):
    with pytest.raises(SystemExit) as exc:
        policy_eval.cli(["--vehicles", "real", "--quick"])
    assert exc.value.code == 2 and "must be one of ideal, realistic" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        policy_eval.cli(["--vehicles", "realistic:drift_m=-1", "--quick"])
    assert exc.value.code == 2 and "drift_m must be finite and >= 0" in capsys.readouterr().err
