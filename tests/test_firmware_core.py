"""The C policy core equals the numpy runtime (policy.runtime) on shared random cases.

The core is compiled with the system C compiler against a freshly generated weights
header, then fed cases through firmware/host/covey_driver.c. Float32 C against the
float64 runtime: the network action and the velocity command (safety filter off)
must agree within 1e-5.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from firmware import cases, hostbuild
from firmware.export_c import export_c_header, header_text
from policy.observation import Observation

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")

TOL = 1e-5
N_SHIPPED_CASES = 1200
N_CONFIG_CASES = 250

CONFIGS = {
    "paper-index": dict(encoding="paper", order="index"),
    "paper-closest-sense": dict(encoding="paper", order="closest_last", sense_range=12.0),
    "sincos-index-scaled": dict(
        encoding="sincos", order="index", dist_scale=10.0, hidden=17, head=(32, 2)
    ),
    "sincos-closest-deep": dict(
        encoding="sincos",
        order="closest_last",
        dist_scale=5.0,
        sense_range=25.0,
        head=(64, 48, 32, 2),
    ),
}


def run_parity(npz, case_list):
    """Max abs errors (action, velocity / cruise) over `case_list`, checking counts too."""
    driver = hostbuild.build_driver(hostbuild.header_for(npz))
    lines, _ = hostbuild.run_driver(driver, "\n".join(map(cases.case_line, case_list)) + "\n")
    assert len(lines) == len(case_list)
    err_action = err_vel = err_vel_m_s = 0.0
    for c, line in zip(case_list, lines, strict=True):
        out = cases.parse_command_output(line)
        assert out["status"] == cases.STATUS["ok"], (line, c)
        vel, action, n_used = cases.runtime_reference(npz, c)
        assert out["n_used"] == n_used
        assert out["n_stale"] == len(c.nbrs) - len(c.fresh_nbrs())
        err_action = max(err_action, float(np.abs(out["action"] - action).max()))
        err_vel = max(err_vel, float(np.abs(out["vel"] - vel).max()) / c.cruise_m_s)
        err_vel_m_s = max(err_vel_m_s, float(np.abs(out["vel"] - vel).max()))
    print(f"(max |vel err| {err_vel_m_s:.3g} m/s at cruise speeds up to 8 m/s)")
    return err_action, err_vel


def test_parity_shipped_weights(capsys):
    rng = np.random.default_rng(2026)
    # every neighbour count 0..40 appears, the rest drawn at random
    case_list = [cases.random_case(rng, n_nbrs=n) for n in range(cases.MAX_NEIGHBOURS + 1)]
    case_list += [cases.random_case(rng) for _ in range(N_SHIPPED_CASES - len(case_list))]
    err_action, err_vel = run_parity(hostbuild.SHIPPED_NPZ, case_list)
    with capsys.disabled():
        print(
            f"\n[firmware parity] shipped weights: {len(case_list)} cases, max |action err| "
            f"{err_action:.3g}, max |vel err|/cruise {err_vel:.3g}"
        )
    assert err_action <= TOL
    assert err_vel <= TOL


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_parity_other_configs(name, tmp_path, capsys):
    npz = cases.write_random_npz(tmp_path / f"{name}.npz", seed=len(name), **CONFIGS[name])
    rng = np.random.default_rng(len(name))
    case_list = [cases.random_case(rng) for _ in range(N_CONFIG_CASES)]
    # more reports than the LSTM takes: the nearest max_neighbours must be chosen alike
    case_list += [cases.random_case(rng, n_nbrs=cases.MAX_INPUTS) for _ in range(20)]
    err_action, err_vel = run_parity(npz, case_list)
    with capsys.disabled():
        print(
            f"\n[firmware parity] {name}: {len(case_list)} cases, max |action err| "
            f"{err_action:.3g}, max |vel err|/cruise {err_vel:.3g}"
        )
    assert err_action <= TOL
    assert err_vel <= TOL


def test_network_alone_matches_runtime(tmp_path):
    """covey_action on encoded sequences equals Network.lstm_last + head_forward."""
    from firmware.cpolicy import CPolicy
    from policy import features
    from policy.runtime import GuidancePolicy

    npz = cases.write_random_npz(tmp_path / "w.npz", encoding="sincos", seed=5)
    cp = CPolicy(npz)
    gp = GuidancePolicy.load(npz)
    rng = np.random.default_rng(5)
    worst = 0.0
    for n in range(0, cases.MAX_NEIGHBOURS + 1, 3):
        seq = rng.normal(size=(n, 5)).astype(np.float32)
        goal = rng.normal(size=2).astype(np.float32)
        ref = features.clip_unit(gp.net.head_forward(gp.net.lstm_last(seq.astype(float)), goal))
        worst = max(worst, float(np.abs(cp.network(seq, goal) - ref).max()))
    assert worst <= TOL


def test_cpolicy_mirrors_guidance_policy_command():
    from firmware.cpolicy import CPolicy, CPolicyError
    from policy.runtime import GuidancePolicy

    cp = CPolicy.load(separation_m=6.0, cruise_speed_m_s=2.5, safety_filter=False)
    gp = GuidancePolicy.load(separation_m=6.0, cruise_speed_m_s=2.5, safety_filter=False)
    rng = np.random.default_rng(3)
    for k in (0, 1, 7, 30):
        pos = rng.uniform(-50, 50, 2)
        nbr = pos + rng.uniform(-60, 60, (k, 2))
        nh = rng.uniform(-np.pi, np.pi, k)
        args = (pos, np.zeros(2), 0.7, pos + [80.0, -30.0], nbr, np.zeros((k, 2)), nh)
        np.testing.assert_allclose(cp.command(*args), gp.command(*args), atol=2.5 * TOL)
    with pytest.raises(CPolicyError) as err:
        cp.command([np.nan, 0.0], [0, 0], 0.0, [1.0, 1.0], np.zeros((0, 2)), np.zeros((0, 2)), [])
    assert err.value.status == "nonfinite"
    # freshness: a stale neighbour is dropped, a stale own state is a fault
    r = cp.evaluate(
        Observation.shaped(
            [0, 0], [0, 0], 0.0, [10, 0], [[3, 0], [0, 3]], [[0, 0]] * 2, [0.0, 0.0]
        ),
        now_s=100.0,
        stamp_s=99.9,
        nbr_stamp_s=[99.8, 90.0],
    )
    assert (r.status, r.n_used, r.n_stale) == ("ok", 1, 1)
    r = cp.evaluate(
        Observation.shaped([0, 0], [0, 0], 0.0, [10, 0], [], [], []), now_s=100.0, stamp_s=98.0
    )
    assert r.status == "stale" and not np.any(r.vel_m_s)


def test_selection_keeps_nearest_and_orders_closest_last(tmp_path):
    """Selection, sense range and ordering are visible in the counts the core reports."""
    npz = cases.write_random_npz(tmp_path / "w.npz", order="closest_last", sense_range=9.0)
    driver = hostbuild.build_driver(hostbuild.header_for(npz))
    # 50 reports on a line north of the vehicle at 1..50 m (sep 3: policy units = metres)
    nbrs = [(float(d), 0.0, 0.0, 0) for d in range(50, 0, -1)]
    c = cases.Case(max_nbrs=5, nbrs=nbrs)
    out = cases.parse_command_output(hostbuild.run_driver(driver, cases.case_line(c) + "\n")[0][0])
    assert (out["n_used"], out["n_far"], out["n_excess"]) == (5, 41, 4)
    vel, action, n_used = cases.runtime_reference(npz, c)
    assert n_used == 5
    assert np.abs(out["action"] - action).max() <= TOL


def test_committed_header_is_up_to_date():
    """firmware/covey_weights.h is what export_c makes of the shipped weights."""
    # Compare as one bool: pytest's assertion diff of two 400 kB strings runs for minutes.
    same = hostbuild.COMMITTED_HEADER.read_text() == header_text(hostbuild.SHIPPED_NPZ)
    assert same, (
        "firmware/covey_weights.h is stale: run "
        "`python -m firmware.export_c policy/weights/policy.npz firmware/covey_weights.h`"
    )


def test_exporter_writes_sizes_and_config(tmp_path):
    npz = cases.write_random_npz(
        tmp_path / "w.npz",
        encoding="sincos",
        order="closest_last",
        hidden=9,
        head=(7, 2),
        dist_scale=4.0,
        sense_range=2.5,
    )
    text = export_c_header(npz, tmp_path / "w.h").read_text()
    for line in (
        "#define COVEY_W_INPUT 5",
        "#define COVEY_W_HIDDEN 9",
        "#define COVEY_W_GOAL 2",
        "#define COVEY_W_HEAD_LAYERS 2",
        "#define COVEY_W_HEAD_MAX_WIDTH 11",
        "#define COVEY_W_ENCODING_SINCOS 1",
        "#define COVEY_W_ORDER_CLOSEST_LAST 1",
        "#define COVEY_W_DIST_SCALE 4.0f",
        "#define COVEY_W_SENSE_RANGE 2.5f",
        "static const float covey_w_lstm_hh_t[324]",
    ):
        assert line in text
    # the weights round-trip exactly through the %.9g literals
    with np.load(npz) as z:
        w = z["head.1.weight"].T.ravel()  # stored transposed (input-major)
    body = text.split("covey_w_head1_wt[14] = {")[1].split("};")[0]
    parsed = np.array(
        [float(v.strip().rstrip("f")) for v in body.split(",") if v.strip()], dtype=np.float32
    )
    assert np.array_equal(parsed, w)


def test_covey_export_writes_the_c_header_and_policy_alone_refuses_it(tmp_path, capsys):
    """`covey export --format c` enters through firmware (policy/ does not import it)."""
    from firmware.export_c import export_cli
    from policy.export import cli as policy_export_cli

    npz = cases.write_random_npz(tmp_path / "w.npz")
    assert export_cli([str(npz), str(tmp_path / "w.h"), "--format", "c"]) == 0
    assert (tmp_path / "w.h").read_text() == header_text(npz)
    assert export_cli([str(npz), str(tmp_path / "copy.npz")]) == 0
    assert (tmp_path / "copy.npz").read_bytes() == npz.read_bytes()
    with pytest.raises(SystemExit) as exc:
        policy_export_cli([str(npz), str(tmp_path / "x.h"), "--format", "c"])
    assert exc.value.code == 2 and "invalid choice: 'c'" in capsys.readouterr().err


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a, c: a.__setitem__("head.0.bias", a["head.0.bias"] * np.nan), "non-finite"),
        (lambda a, c: a.__setitem__("lstm.weight_ih", a["lstm.weight_ih"][:, :2]), "LSTM shapes"),
        (lambda a, c: c.__setitem__("encoder", "map"), "lstm encoder"),
        (lambda a, c: c.__setitem__("encoding", "polar"), "encoding"),
        (lambda a, c: (a.pop("head.2.weight"), a.pop("head.2.bias")), "2 outputs"),
    ],
)
def test_exporter_rejects_bad_weights(tmp_path, change, message):
    npz = cases.write_random_npz(tmp_path / "w.npz")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    cfg = json.loads(str(arrays.pop("config")))
    change(arrays, cfg)
    np.savez(tmp_path / "bad.npz", config=np.array(json.dumps(cfg)), **arrays)
    with pytest.raises(ValueError, match=message):
        export_c_header(tmp_path / "bad.npz", tmp_path / "bad.h")


def test_c_unit_tests_pass_under_sanitizers():
    """firmware/host/covey_unit.c: traffic table, heading, NULLs, ties, wrap edges."""
    unit = hostbuild.build_unit(hostbuild.header_for(hostbuild.SHIPPED_NPZ))
    lines, stderr = hostbuild.run_driver(unit, "")
    assert lines and lines[-1].endswith("checks passed"), (lines, stderr)
    assert "runtime error" not in stderr and "Sanitizer" not in stderr, stderr
