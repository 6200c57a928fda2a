"""Values a CLI accepts are used, or refused with the real reason (exit 2, before anything starts)."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("start", ["1e30,0", "0,-2e6"])
def test_agent_refuses_a_start_no_state_could_carry(start, capsys) -> None:
    from agent import agent_cli as cli

    with pytest.raises(SystemExit) as exc:
        cli.cli(["--id", "1", "--start-ne-m", start])  # refused before any backend or mesh exists
    assert exc.value.code == 2 and "each coordinate must be within" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["-inf", "-NaN", "-infinity"])
def test_cmd_says_a_non_finite_coordinate_is_the_problem(bad, capsys) -> None:
    from groundstation.ops import cmd_cli

    with pytest.raises(SystemExit) as exc:
        cmd_cli(["goto", bad, "0", "-5", "--to", "1"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "must be finite numbers" in err and "required" not in err


# -- a flag that is accepted is used, or refused with the reason -------------------------------


def _refused(fn, argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        fn(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def test_agent_tells_the_policy_the_berth_it_was_given(capsys) -> None:
    """--policy-separation-m reaches the agent's guidance (the filter keeps --separation-m); a
    berth that is not a positive number is refused in one line."""
    from agent import agent_cli as cli
    from policy.runtime import FILTERED_BERTH_SHARE

    args = cli.parser().parse_args(["--id", "3", "--policy-separation-m", "1.5"])
    guidance = cli.config_from_args(args).guidance
    assert guidance.policy_separation_m == 1.5 and guidance.separation_m == 3.0
    assert guidance.load_policy().dist_scale_m == pytest.approx(0.5)
    default = cli.config_from_args(cli.parser().parse_args(["--id", "3"])).guidance
    assert default.policy_separation_m is None
    assert default.told_separation_m == pytest.approx(3.0 * FILTERED_BERTH_SHARE)
    line = _refused(cli.cli, ["--id", "1", "--policy-separation-m", "0"], capsys)
    assert "policy_separation_m must be a positive number" in line, line


def test_record_refuses_a_key_file_it_would_not_use(tmp_path, capsys) -> None:
    from tools.record_cli import record_cli

    line = _refused(record_cli, ["-o", str(tmp_path / "r.mcap"), "--key-file", "k"], capsys)
    assert "--key-file is refused" in line and "signs nothing" in line


def test_replay_refuses_a_key_file_a_replay_cannot_sign_with(tmp_path, capsys) -> None:
    from tools.replay_cli import replay_cli

    line = _refused(replay_cli, [str(tmp_path / "f.mcap"), "--key-file", "k"], capsys)
    assert "--key-file is refused: a replay cannot be signed" in line
    assert "open-mode fleet" in line


@pytest.mark.parametrize("name", ["record", "replay", "foxglove", "fleet-sim", "router"])
def test_the_refusal_is_in_the_help(name, capsys) -> None:
    import covey_cli

    text = " ".join(covey_cli.parser_of(name).format_help().split())
    assert "--key-file" in text and "refused:" in text


def test_a_key_in_the_environment_is_noted_not_silently_dropped(
    tmp_path, capsys, monkeypatch
) -> None:
    from cli.options import key_env_note
    from tools.record_cli import RECORD_NO_KEY, record_cli, record_parser

    key_env_note(record_parser(), RECORD_NO_KEY, env={})
    assert capsys.readouterr().err == ""
    key_env_note(record_parser(), RECORD_NO_KEY, env={"COVEY_FLEET_KEY_FILE": "/k"})
    err = capsys.readouterr().err
    assert err.startswith("covey record: note: $COVEY_FLEET_KEY_FILE is not used: a recorder")
    # And a real (standalone, 0.3 s) recording says so, then records.
    monkeypatch.setenv("COVEY_FLEET_KEY_FILE", "/nonexistent/member.key")
    out = tmp_path / "r.mcap"
    argv = ["-o", str(out), "--duration-s", "0.3", "--mesh-mode", "router"]
    assert record_cli([*argv, "--listen", "tcp/127.0.0.1:0"]) == 0
    assert "is not used" in capsys.readouterr().err and out.is_file()


@pytest.mark.parametrize(
    ("name", "argv", "says"),
    [
        ("foxglove", ["--key-file", "k"], "neither signs nor checks"),
        ("fleet-sim", ["--key-file", "k"], "fleet-sim is the open-mode host"),
        ("keygen", ["push", "--key-file", "k"], "signed by the authority key"),
        ("record", ["--json"], "--json prints the summary of --info"),
        ("record", ["--info", "f.mcap", "--fleet", "x"], "--fleet: not used with --info"),
        ("record", ["--foxglove-from", "a", "--duration-s", "3"], "not used with --foxglove"),
        ("record", ["--no-foxglove", "--separation-m", "2"], "which --no-foxglove leaves out"),
        ("sitl", ["--separation-m", "4"], "onboard policy, which needs --onboard"),
        ("sitl", ["--weights", "w.npz"], "needs --onboard"),
        ("sitl", ["--policy-separation-m", "1"], "needs --onboard"),
        ("sitl", ["--no-sparse-rule"], "needs --onboard"),
        ("agent", ["--id", "1", "--vehicle", "mavsdk:", "--start-ne-m", "1,2"], "is where it is"),
        ("agent", ["--id", "1", "--vehicle", "relay:", "--policy", "p.npz"], "runs the policy"),
        ("agent", ["--id", "1", "--vehicle", "relay:", "--trace-guidance"], "onboard"),
        ("agent", ["--id", "1", "--vehicle", "relay:", "--policy-separation-m", "1"], "onboard"),
        ("agent", ["--id", "1", "--vehicle", "relay:", "--no-sparse-rule"], "onboard"),
        ("eval", ["--merge", "a.json", "--quick"], "--merge combines results files"),
        ("train", ["--episodes", "500", "--episodes-k", "1"], "say the same thing"),
        ("router", ["--key-file", "k"], "a router holds no member key"),
        ("router", ["--fleet", "x"], "routes every fleet's keys"),
        ("router", ["--mesh-mode", "peer"], "always a Zenoh router"),
        (
            "agent",
            ["--id", "1", "--mesh-mode", "client", "--listen", "tcp/127.0.0.1:0"],
            "accepts no links",
        ),
    ],
)
def test_a_flag_that_would_be_ignored_is_refused(name, argv, says, capsys) -> None:
    import importlib

    import covey_cli

    module, func, _ = covey_cli.SUBCOMMANDS[name]
    line = _refused(getattr(importlib.import_module(module), func), argv, capsys)
    assert says in line, line


def test_replay_refuses_flags_of_the_other_mode(tmp_path, capsys) -> None:
    from tools.replay_cli import replay_cli

    rec = tmp_path / "f.mcap"
    rec.write_bytes(b"")  # exists: the refusal comes before the recording is read
    line = _refused(replay_cli, [str(rec), "--policy", "p", "--vehicle", "1", "--loop"], capsys)
    assert "--loop: closed-loop replay (--policy) publishes nothing" in line
    line = _refused(replay_cli, [str(rec), "--json-out", "x.json"], capsys)
    assert "--json-out: closed-loop replay only" in line


def test_the_recorder_joins_as_a_client_unless_told_otherwise() -> None:
    """A router hands its clients a new vehicle's states from the first one; a peer recorder
    hears it only once their gossip link is up (tests/test_drill_record.py)."""
    from cli.options import mesh_config
    from tools.record_cli import record_parser

    p = record_parser()
    assert mesh_config(p.parse_args(["-o", "f.mcap"]), p).mode == "client"
    assert "client, of the router" in " ".join(p.format_help().split())
    peer = mesh_config(p.parse_args(["-o", "f.mcap", "--mesh-mode", "peer"]), p)
    assert peer.mode == "peer" and peer.listen == ("tcp/127.0.0.1:0",)
