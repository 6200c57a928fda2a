"""Every covey CLI's options, checked from the parsers themselves (covey_cli.SUBCOMMANDS), and the
shared options module (cli/options.py): mesh endpoints, renamed and refused flags, flags
built from a config dataclass, stopping on signals."""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import threading

import pytest

import covey_cli
from cli import options as cli_options
from cli.options import Refused

FLAG_UNITS = tuple(sorted({end.replace("_", "-") for end in cli_options.UNIT_SUFFIXES}))
"""A quantity flag ends in one of these: -s, -m, -m-s, -m-s2, -hz, -pct, -rad, -deg, ..."""

NO_UNIT_SUFFIX: dict[str, set[tuple[str, str]]] = {
    "dimensionless: PPO hyper-parameters, reward weights and scales, an action bias": {
        ("train", f"--{name}")
        for name in (
            "lr",
            "gamma",
            "gae-lambda",
            "clip-coef",
            "vf-coef",
            "ent-coef",
            "max-grad-norm",
            "init-log-std",
            "reward-scale",
            "w-acc",
            "w-tme",
            "w-prog",
            "fwd-bias",
            "lone-anchor",
        )
    },
    "a share of arenas, 0 to 1 (a probability, not a percentage)": {("train", "--conflict-share")},
    "a relative padding on the separation (0.2 = 20 % more), as SafetyConfig.margin": {
        ("train", "--filter-margin")
    },
    "ratios of distances: the network's zoom of the arena, the share of the separation told": {
        ("train", "--told-scale"),
        ("train", "--filtered-told-share"),
    },
    "a count, in thousands (the -k is its scale)": {("train", "--episodes-k")},
    "a confidence factor in standard deviations (k of k sqrt(si^2 + sj^2)), no unit": {
        ("eval", "--sigma-k")
    },
    "a ratio of real time (2 = twice as fast), no unit": {("replay", "--speed")},
    "a share of the speed limit (2 = twice max_speed_m_s), as SafetyConfig.recover_speed_share": {
        ("eval", "--recover-speed-share")
    },
    "LAT,LON,ALT: three numbers in degrees, degrees, metres, named by the metavar": {
        ("agent", "--origin"),
        ("fleet-sim", "--origin"),
        ("sitl", "--home"),
        ("record", "--origin"),
        ("foxglove", "--origin"),
        ("plan", "--origin"),
    },
}
ALLOWED = {flag for flags in NO_UNIT_SUFFIX.values() for flag in flags}


def parsers(p: argparse.ArgumentParser, path: str):
    """`p` and every subparser below it (covey cmd's and covey keygen's verbs)."""
    yield path, p
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for verb, sub in action.choices.items():
                yield from parsers(sub, f"{path} {verb}")


def _is_number(value: object) -> bool:
    if isinstance(value, float):
        return True
    if isinstance(value, tuple) and value:
        return all(isinstance(v, float) for v in value)
    if dataclasses.is_dataclass(value):
        return all(isinstance(getattr(value, f.name), float) for f in dataclasses.fields(value))
    return False


def takes_numbers(action: argparse.Action) -> bool:
    """True when the option's value is a float (or floats): its type turns "1.5" (or "1.5,2.5",
    "1.5,2.5,3.5") into one."""
    if not action.option_strings or action.nargs == 0 or isinstance(action, Refused):
        return False
    if action.type is float:
        return True
    if action.type is None or action.type in (int, str):
        return False
    for text in ("1.5", "1.5,2.5", "1.5,2.5,3.5"):
        try:
            if _is_number(action.type(text)):
                return True
        except (argparse.ArgumentTypeError, ValueError, TypeError):
            pass
    return False


def quantity_options() -> list[tuple[str, str]]:
    out = []
    for name in covey_cli.SUBCOMMANDS:
        for path, p in parsers(covey_cli.parser_of(name), name):
            for action in p._actions:
                if takes_numbers(action):
                    out.append((path.split()[0], max(action.option_strings, key=len)))
    return out


def test_every_subcommand_has_a_parser_builder() -> None:
    for name in covey_cli.SUBCOMMANDS:
        p = covey_cli.parser_of(name)
        assert isinstance(p, argparse.ArgumentParser) and p.prog == f"covey {name}", name


def test_every_quantity_flag_ends_in_its_unit() -> None:
    found = quantity_options()
    assert ("sitl", "--cruise-speed-m-s") in found and ("agent", "--start-ne-m") in found
    missing = sorted(
        {(cmd, flag) for cmd, flag in found if not flag.endswith(FLAG_UNITS)} - ALLOWED
    )
    assert not missing, f"quantity flags without a unit suffix {FLAG_UNITS}: {missing}"
    stale = sorted(ALLOWED - set(found))
    assert not stale, f"allowlisted flags that no longer exist or take no number: {stale}"


RENAMED = [
    ("record", ["--duration", "5"], "--duration was renamed --duration-s"),
    ("sitl", ["--cruise-speed", "5"], "--cruise-speed was renamed --cruise-speed-m-s"),
    ("sitl", ["--separation", "4"], "--separation was renamed --separation-m"),
    ("sitl", ["--accel=3"], "--accel was renamed --accel-m-s2"),
    ("sitl", ["--duration", "1"], "--duration was renamed --duration-s"),
    ("agent", ["--id", "1", "--start=1,2"], "--start was renamed --start-ne-m"),
    ("fleet-sim", ["--start", "0,0"], "--start was renamed --start-ne-m"),
    ("replay", ["x.mcap", "--start", "3"], "--start was renamed --start-s"),
    ("replay", ["x.mcap", "--presence-wait", "3"], "--presence-wait was renamed"),
    ("eval", ["--dt", "0.1"], "--dt was renamed --dt-s"),
    ("eval", ["--policy-separation", "3.5"], "--policy-separation was renamed"),
    ("cmd", ["hold", "--to", "1", "--timeout", "1"], "--timeout was renamed --timeout-s"),
]


@pytest.mark.parametrize(("name", "argv", "message"), RENAMED, ids=[r[2][:28] for r in RENAMED])
def test_an_old_flag_name_is_refused_in_one_line(name, argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        covey_cli.parser_of(name).parse_args(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err, err
    assert "--duration " not in covey_cli.parser_of("record").format_help()  # hidden


# -- joining the mesh ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name", ["agent", "gcs", "status", "foxglove", "fleet-sim", "record", "router"]
)
def test_connect_and_listen_split_on_commas_in_every_cli(name) -> None:
    p = covey_cli.parser_of(name)
    base = ["--id", "3"] if name == "agent" else []
    base += ["--mesh-mode", "peer"] if name == "record" else []  # a recorder is a client
    args = p.parse_args(
        [*base, "--connect", "tcp/10.0.0.1:7447,tcp/10.0.0.2:7447", "--connect", "tcp/h:1"]
        + ["--listen", "tcp/127.0.0.1:0,tcp/127.0.0.1:7448"]
    )
    cfg = cli_options.mesh_config(args, p)
    assert cfg.connect == ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447", "tcp/h:1")
    assert cfg.listen == ("tcp/127.0.0.1:0", "tcp/127.0.0.1:7448")


def test_the_agent_joins_every_endpoint_of_a_comma_list() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    args = p.parse_args(["--id", "3", "--connect", "tcp/10.0.0.1:7447,tcp/10.0.0.2:7447"])
    cfg = agent_cli.config_from_args(args, p)
    assert cfg.mesh.connect == ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447")
    router = agent_cli.config_from_args(p.parse_args(["--id", "3", "--mesh-mode", "router"]), p)
    assert router.mesh.connect == () and router.mesh.listen == ("tcp/127.0.0.1:7447",)


def test_a_bad_endpoint_is_a_value_error_without_a_parser_and_exit_2_with_one(capsys) -> None:
    p = covey_cli.parser_of("status")
    args = p.parse_args(["--connect", "tcp/127.0.0.1:99999"])
    with pytest.raises(ValueError, match="outside 0..65535"):
        cli_options.mesh_config(args)
    with pytest.raises(SystemExit) as exc:
        cli_options.mesh_config(args, p)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "covey status: error:" in err


def test_a_client_refuses_to_listen_and_a_router_defaults_to_the_covey_port(capsys) -> None:
    p = covey_cli.parser_of("agent")
    args = p.parse_args(["--id", "3", "--mesh-mode", "client", "--listen", "tcp/127.0.0.1:0"])
    with pytest.raises(ValueError, match="a client accepts no links"):
        cli_options.mesh_config(args)
    client = p.parse_args(["--id", "3", "--mesh-mode", "client", "--connect", "tcp/h:7447"])
    assert cli_options.mesh_config(client, p).connect == ("tcp/h:7447",)
    r = covey_cli.parser_of("router")
    cfg = cli_options.mesh_config(r.parse_args([]), r)
    assert (cfg.mode, cfg.listen, cfg.connect) == ("router", ("tcp/127.0.0.1:7447",), ())
    cfg = cli_options.mesh_config(r.parse_args(["--connect", "tcp/a:1,tcp/b:2"]), r)
    assert cfg.connect == ("tcp/a:1", "tcp/b:2")


def test_key_file_comes_from_the_flag_then_the_environment() -> None:
    args = argparse.Namespace(key_file=None)
    assert cli_options.key_file_path(args, env={}) is None
    assert cli_options.key_file_path(args, env={"COVEY_FLEET_KEY_FILE": "/k"}) == "/k"
    args.key_file = ""  # an empty flag is the user's (and refused later), not the variable's
    assert cli_options.key_file_path(args, env={"COVEY_FLEET_KEY_FILE": "/k"}) == ""


# -- flags from a config dataclass ----------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Example:
    """A config to build flags from."""

    cruise_speed_m_s: float = 2.0
    """How fast: the help text."""
    count: int = 3
    """How many."""
    name: str | None = None
    """A name, or none."""
    fast: bool = False
    """Go fast."""
    modes: tuple = ("a", "b")
    """Which modes."""


def test_config_flags_come_from_fields_and_their_docstrings() -> None:
    p = argparse.ArgumentParser(prog="x")
    cli_options.add_config_flags(p, Example)
    text = p.format_help()
    assert "--cruise-speed-m-s M/S" in text and "How fast: the help text. (default: 2.0)" in text
    assert "--fast, --no-fast" in text
    cfg = cli_options.config_from_flags(Example, p.parse_args([]))
    assert cfg == Example()
    args = p.parse_args(
        ["--cruise-speed-m-s", "4", "--count", "5", "--name", "n", "--fast", "--modes", "c,d"]
    )
    assert cli_options.config_from_flags(Example, args) == Example(4.0, 5, "n", True, ("c", "d"))
    assert cli_options.config_from_flags(Example, args, count=9).count == 9


@pytest.mark.parametrize("bad", ["nan", "inf", "x"])
def test_a_config_flag_refuses_a_non_finite_number_naming_its_unit(bad, capsys) -> None:
    p = argparse.ArgumentParser(prog="x")
    cli_options.add_config_flags(p, Example, only=["cruise_speed_m_s"])
    with pytest.raises(SystemExit):
        p.parse_args(["--cruise-speed-m-s", bad])
    assert "m/s" in capsys.readouterr().err


def test_config_flags_only_and_skip_name_real_fields() -> None:
    with pytest.raises(TypeError, match="no fields"):
        cli_options.add_config_flags(argparse.ArgumentParser(), Example, only=["speed"])


# -- stopping on signals --------------------------------------------------------------------------
def test_sigterm_and_sigint_set_the_event_and_the_old_handlers_come_back() -> None:
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with cli_options.stop_on_signals() as stop:
        assert not stop.is_set()
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5.0)
    with cli_options.stop_on_signals() as stop:
        os.kill(os.getpid(), signal.SIGINT)  # no KeyboardInterrupt
        assert stop.wait(5.0)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_off_the_main_thread_the_event_is_plain() -> None:
    seen = []

    def run() -> None:
        with cli_options.stop_on_signals() as stop:
            seen.append(isinstance(stop, threading.Event) and not stop.is_set())

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen == [True]
