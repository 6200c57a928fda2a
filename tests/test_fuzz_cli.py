"""Fuzz the command-line parsers of `covey agent`, `covey cmd`, `covey sitl` and `covey keygen`.

Random argument lists built from each parser's own options and hostile values (NaN, inf, huge,
negative, empty, unicode, separators). Each must end in a parsed config or a clear usage error:
argparse's SystemExit(2) with a message, or ValueError / InputError with a message. Nothing
reaches the network: only parsing and config building run.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import random
import re

import pytest

SEED = 8
N_PER_PARSER = 1500
VALUES = [
    "0",
    "1",
    "-1",
    "3",
    "65000",
    "65001",
    "1e309",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "",
    " ",
    "1,2",
    "1,2,3",
    "1,,2",
    "nan,0",
    "0,inf,0",
    "abc",
    "ä✈",
    "--",
    "-",
    "all",
    "1-4",
    "4-1",
    "1-100000",
    "tcp/127.0.0.1:7447",
    "tcp/",
    "udp/[::1]:1",
    "no-slash",
    "peer",
    "client",
    "router",
    "sim",
    "mavsdk:",
    "relay:x",
    "bogus:1",
    "rate=3,loss=0.2",
    "rate=-1",
    "xbee",
    "0x10",
    "1_000",
    "9" * 400,
    "\x00",
    "-5",
    "-0.0",
]


def options_of(p: argparse.ArgumentParser) -> list[str]:
    opts = [s for a in p._actions for s in a.option_strings if s not in ("-h", "--help")]
    return sorted(set(opts))


def random_argv(rng: random.Random, opts: list[str], prefix: list[str] | None = None) -> list[str]:
    argv = list(prefix or [])
    for _ in range(rng.randint(0, 8)):
        r = rng.random()
        if r < 0.6:
            argv.append(rng.choice(opts))
            if rng.random() < 0.85:
                argv.append(rng.choice(VALUES))
        elif r < 0.8:
            argv.append(rng.choice(VALUES))
        else:
            argv.append(f"{rng.choice(opts)}={rng.choice(VALUES)}")
    return argv


def expect_clean(
    fn, argv: list[str], ok_errors: tuple[type[BaseException], ...], stats: dict[str, int]
) -> None:
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            fn(argv)
    except SystemExit as exc:
        assert exc.code == 2 and "error:" in err.getvalue(), (argv, exc.code, err.getvalue())
        stats["usage_error"] += 1
    except ok_errors as exc:
        assert str(exc), argv
        stats["value_error"] += 1
    else:
        stats["parsed"] += 1


@pytest.fixture
def stats():
    s = {"parsed": 0, "usage_error": 0, "value_error": 0}
    yield s
    print(f"{sum(s.values())} argument lists: {s}")


def test_covey_agent_parser(stats) -> None:
    from agent import agent_cli as cli

    def parse(argv: list[str]) -> None:
        cli.config_from_args(cli.parser().parse_args(argv))

    rng = random.Random(SEED)
    opts = options_of(cli.parser())
    for _ in range(N_PER_PARSER):
        expect_clean(
            parse,
            random_argv(rng, opts, ["--id", rng.choice(VALUES)] if rng.random() < 0.7 else None),
            (ValueError,),
            stats,
        )
    assert stats["parsed"] > 0 and stats["usage_error"] > 100


def test_covey_cmd_parser(stats) -> None:
    ops = pytest.importorskip("groundstation.ops")
    from cli.options import mesh_config
    from groundstation import inputs

    def parse(argv: list[str]) -> None:
        p = ops.cmd_parser()
        args = p.parse_args(argv)
        ops._request(args)
        inputs.targets(args.to)
        mesh_config(args, p)

    rng = random.Random(SEED + 1)
    verbs = ["takeoff", "land", "hold", "return", "goto", "goto-global", "kill", "fly", ""]
    opts = ["--to", "--timeout-s", "--yes", "--fleet", "--connect", "--listen", "--mesh-mode"]
    for _ in range(N_PER_PARSER):
        prefix = (
            [rng.choice(verbs)]
            + [rng.choice(VALUES) for _ in range(rng.randint(0, 3))]
            + ["--to", rng.choice(VALUES)]
        )
        expect_clean(parse, random_argv(rng, opts, prefix), (inputs.InputError, ValueError), stats)
    assert stats["parsed"] > 0 and stats["usage_error"] > 100


def test_covey_sitl_parser(stats) -> None:
    sitl_cli = pytest.importorskip("firmware.sitl.sitl_cli")
    rng = random.Random(SEED + 2)
    opts = options_of(sitl_cli.parser())
    for _ in range(N_PER_PARSER):
        expect_clean(sitl_cli.config_from_args, random_argv(rng, opts), (ValueError,), stats)
    assert stats["parsed"] > 10


def test_covey_keygen_parser(stats, tmp_path, monkeypatch) -> None:
    from groundstation.keygen_cli import VERBS, keygen_cli

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    rng = random.Random(SEED + 3)
    verbs = [v for v in VERBS if v != "push"]  # push joins a mesh: tested end to end
    for _ in range(300):
        argv = random_argv(
            rng, ["--dir", "--fleet", "vehicle", "station", "-x"], prefix=[rng.choice(verbs)]
        )
        expect_clean(keygen_cli, argv, (ValueError,), stats)
    assert stats["parsed"] > 10


@pytest.mark.parametrize("bad", ["nan", "inf", "0", "-1"])
def test_agent_refuses_a_bad_duration_before_starting(bad, capsys) -> None:
    from agent import agent_cli as cli

    with pytest.raises(SystemExit) as exc:
        cli.cli(["--id", "1", "--duration-s", bad])  # refused before any backend or mesh exists
    assert exc.value.code == 2 and "--duration-s must be a positive" in capsys.readouterr().err


def test_covey_exit_status_from_what_a_subcommand_returns(monkeypatch, capsys) -> None:
    """`covey train`/`covey eval` return their results (a dict): that is success, not a crash."""
    import sys
    import types

    import covey_cli

    fake = types.ModuleType("covey_fake_sub")
    fake.returns = None
    fake.cli = lambda argv: fake.returns
    monkeypatch.setitem(sys.modules, "covey_fake_sub", fake)
    monkeypatch.setitem(covey_cli.SUBCOMMANDS, "fake", ("covey_fake_sub", "cli", "test"))
    for returned, status in (({"success": 1.0}, 0), (None, 0), (0, 0), (3, 3), (True, 0)):
        fake.returns = returned
        assert covey_cli.main(["fake"]) == status, returned
    assert covey_cli.main(["no-such-command"]) == 2
    assert "unknown command" in capsys.readouterr().err


# -- files and endpoints: one line, exit 2, never a traceback ----------------------------------
def bad_setups(tmp_path) -> dict[str, list[str]]:
    """Hostile --zenoh-config files, endpoints and key files, as argument lists."""
    import socket

    d = tmp_path / "bad"
    d.mkdir(exist_ok=True)
    files = {
        "not-utf8.json5": b"\xff\xfe{ mode: 'peer' }",
        "bad.json5": b"{ mode: ",
        "unknown-field.json5": b"{ no_such_field: 1 }",
        "wrong-type.json5": b"{ mode: 3 }",
        "mtls-no-certs.json5": b'{ transport: { link: { tls: { enable_mtls: true, root_ca_certificate: "/nonexistent/ca.pem" } } } }',
    }
    for name, data in files.items():
        (d / name).write_bytes(data)
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    bad_setups.keep = busy  # held open for the whole test
    cases = {
        "config missing": ["--zenoh-config", str(d / "missing.json5")],
        "config is a directory": ["--zenoh-config", str(d)],
        "config empty path": ["--zenoh-config", ""],
        **{
            f"config {name}": ["--zenoh-config", str(d / name)]
            for name in files
            if "mtls" not in name
        },
        "config mtls without certificates": [
            "--zenoh-config",
            str(d / "mtls-no-certs.json5"),
            "--listen",
            "tls/127.0.0.1:0",
            "--connect",
            "tls/127.0.0.1:1",
        ],
        "connect port 99999": ["--connect", "tcp/127.0.0.1:99999"],
        "listen port 99999": ["--listen", "tcp/127.0.0.1:99999"],
        "listen on a busy port": [
            "--listen",
            f"tcp/127.0.0.1:{busy.getsockname()[1]}",
            "--connect",
            "tcp/127.0.0.1:1",
        ],
    }
    (d / "garbage.key").write_text("not a key")
    (d / "garbage.key").chmod(0o600)
    keys = {
        "key empty path": ["--key-file", ""],
        "key missing": ["--key-file", str(d / "missing.key")],
        "key malformed": ["--key-file", str(d / "garbage.key")],
        "key is a directory": ["--key-file", str(d)],
    }
    return cases, keys


LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ ")
"""A log record (cli.options.setup_logging), not a line the CLI wrote."""


def run_one_line(fn, argv: list[str], strict: bool = False) -> str:
    """Run a CLI that must refuse `argv`: exit 2, one error line, no traceback; `strict`:
    nothing else on stderr either, but log records."""
    err = io.StringIO()
    with (
        contextlib.redirect_stderr(err),
        contextlib.redirect_stdout(io.StringIO()),
        pytest.raises(SystemExit) as exc,
    ):
        fn(argv)
    text = err.getvalue()
    errors = [ln for ln in text.splitlines() if "error" in ln.lower()]
    assert exc.value.code == 2, (argv, exc.value.code, text)
    assert "Traceback" not in text, (argv, text)
    assert len(errors) == 1 and "error:" in errors[0], (argv, text)
    if strict:
        lines = [ln for ln in text.splitlines() if ln.strip() and not LOG_LINE.match(ln)]
        assert len(lines) == 1, (argv, text)
    return errors[0]


def test_bad_files_and_endpoints_are_one_line_exit_2_in_every_subcommand(tmp_path) -> None:
    from agent import agent_cli
    from groundstation import gcs_cli, ops
    from tools import record_cli, router_cli

    mesh_cases, key_cases = bad_setups(tmp_path)
    subcommands = {
        "agent": (agent_cli.cli, ["--id", "1", "--duration-s", "1"], True),
        "gcs": (gcs_cli.cli, ["--port", "0"], True),
        "cmd": (ops.cmd_cli, ["hold", "--to", "1", "--timeout-s", "0.5"], True),
        "status": (ops.status_cli, ["--listen-s", "0.1"], True),
        "router": (router_cli.cli, [], False),
        "record": (
            record_cli.record_cli,
            ["-o", str(tmp_path / "r.mcap"), "--duration-s", "0.5"],
            False,
        ),
    }
    seen = 0
    for name, (fn, base, takes_key) in subcommands.items():
        cases = {**mesh_cases, **(key_cases if takes_key else {})}
        for case, extra in cases.items():
            line = run_one_line(fn, [*base, *extra])
            seen += 1
            print(f"covey {name} [{case}]: {line}")
    assert seen == 6 * len(mesh_cases) + 4 * len(key_cases)
