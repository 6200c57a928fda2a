"""Fuzz the files covey is handed: key files, rosters, Zenoh JSON5 configs, npz weights and MCAP
recordings, through the real CLIs, and the waits for a router that must end.

Every bad file gives exit status 2 and one line on stderr: no traceback, no crash (a negative
return code), no hang. A cut-off or corrupted recording is used as far as it can be read, with
a warning that counts what was kept, and exit status PARTIAL_EXIT (1). Many inputs go through
in-process `cli(argv)` calls (cheap); a few through real subprocesses: the inputs that crashed
a process outright (Zenoh's parser overflowing its stack), and the signals and durations that
must end a wait for a router that never answers.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_fuzz_cli import LOG_LINE, run_one_line

from comms.schema import Event, VehicleState
from comms.session import free_tcp_port
from kit.safe_load import MAX_DEPTH, nesting_depth
from recording.record import PARTIAL_EXIT, McapSink, read_recording
from trust.authority import ROSTER, Authority

REPO = Path(__file__).resolve().parent.parent
WEIGHTS = REPO / "policy" / "weights" / "policy.npz"
SEED = 34


def strict_one_line(fn, argv: list[str]) -> str:
    """Exit 2, one error line, no traceback, and nothing else on stderr but log records."""
    return run_one_line(fn, argv, strict=True)


def text_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.strip() and not LOG_LINE.match(ln)]


def covey(*argv: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "covey_cli", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
    )


# -- the scanner ---------------------------------------------------------------------------------
def test_nesting_depth_skips_strings_and_comments() -> None:
    assert nesting_depth("{ a: [1, {b: 2}] }") == 3
    assert nesting_depth("{ a: \"[[[[[[\", b: '{{{{', /* [[[[ */ // {{{{\n c: [] }") == 2
    assert nesting_depth(r'{ a: "\"[[[[" }') == 1
    assert nesting_depth("[" * 1000, limit=MAX_DEPTH) == MAX_DEPTH + 1  # stops counting early
    for f in (REPO / "comms" / "zenoh_configs").glob("*.json5"):
        assert nesting_depth(f.read_text()) <= 8, f


# -- key files and rosters -------------------------------------------------------------------------
def bad_key_files(d: Path, rng: random.Random) -> dict[str, bytes]:
    good = {
        "covey": "member-key",
        "version": 1,
        "fleet": "covey",
        "role": "vehicle",
        "id": 1,
        "private_key": "00" * 32,
        "authority_public_key": "00" * 32,
        "roster": "00",
    }
    files = {
        "deep-array": b'{"covey": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
        "deep-object": b'{"a":' * 5_000 + b"1" + b"}" * 5_000,
        "just-too-deep": b"[" * (MAX_DEPTH + 1) + b"]" * (MAX_DEPTH + 1),
        "huge": b'{"covey": "' + b"x" * 1_100_000 + b'"}',
        "binary": bytes(rng.getrandbits(8) for _ in range(4096)),
        "nul": b"\x00" * 64,
        "empty": b"",
        "not-utf8": b'{"covey": "\xff\xfe"}',
        "list": b"[1, 2, 3]",
        "number": b"1e400",
        "huge-int": b'{"id": ' + b"9" * 5000 + b"}",
        "string": b'"member-key"',
        "torn": json.dumps(good).encode()[:40],
    }
    for field, bad in [
        ("fleet", 3),
        ("fleet", "no/slash"),
        ("role", ["vehicle"]),
        ("role", "pilot"),
        ("id", "1"),
        ("id", True),
        ("id", 10**30),
        ("id", -1),
        ("private_key", "zz"),
        ("private_key", "00" * 31),
        ("private_key", {"a": [1]}),
        ("authority_public_key", None),
        ("roster", "0" * 7),
        ("roster", "ff" * 500),
        ("covey", None),
    ]:
        files[f"{field}={str(bad)[:12]}"] = json.dumps({**good, field: bad}).encode()
    for name, data in files.items():
        path = d / f"{re.sub(r'[^a-z0-9=-]', '_', name)}.key"
        path.write_bytes(data)
        path.chmod(0o600)
    return {name: d / f"{re.sub(r'[^a-z0-9=-]', '_', name)}.key" for name in files}


def test_every_bad_key_file_is_one_line_exit_2_in_every_subcommand(tmp_path) -> None:
    from agent import agent_cli
    from groundstation import gcs_cli, ops

    files = bad_key_files(tmp_path, random.Random(SEED))
    subcommands = {
        "agent": (agent_cli.cli, ["--id", "1", "--duration-s", "1"]),
        "gcs": (gcs_cli.cli, ["--port", "0"]),
        "cmd": (ops.cmd_cli, ["hold", "--to", "1", "--timeout-s", "0.5"]),
        "status": (ops.status_cli, ["--listen-s", "0.1"]),
    }
    seen = 0
    for name, (fn, base) in subcommands.items():
        for case, path in files.items():
            line = strict_one_line(fn, [*base, "--key-file", str(path)])
            assert "RecursionError" not in line, (name, case, line)
            seen += 1
    # --ids reads vehicle-<id>.key from a directory
    key_dir = tmp_path / "keys"
    key_dir.mkdir()
    for case, path in files.items():
        (key_dir / "vehicle-1.key").write_bytes(path.read_bytes())
        (key_dir / "vehicle-1.key").chmod(0o600)
        line = strict_one_line(
            agent_cli.cli, ["--ids", "1-2", "--key-dir", str(key_dir), "--duration-s", "1"]
        )
        assert "vehicle-1.key" in line, (case, line)
        seen += 1
    assert seen == 5 * len(files)


def test_bad_authority_files_and_rosters_are_one_line_exit_2_in_keygen(tmp_path) -> None:
    from groundstation.keygen_cli import keygen_cli

    files = bad_key_files(tmp_path, random.Random(SEED + 1))
    d = tmp_path / "fleet"
    Authority.init(d, "covey")
    good_authority = (d / "authority.key").read_bytes()
    for case, path in files.items():
        (d / "authority.key").write_bytes(path.read_bytes())
        line = strict_one_line(keygen_cli, ["list", "--dir", str(d)])
        assert "authority" in line, (case, line)
    (d / "authority.key").write_bytes(good_authority)
    good_roster = (d / ROSTER).read_bytes()
    rng = random.Random(SEED + 2)
    rosters = {
        "empty": b"",
        "binary": bytes(rng.getrandbits(8) for _ in range(2048)),
        "huge": b"\x05" * 2_000_000,
        "torn": good_roster[: len(good_roster) // 2],
        "flipped": good_roster[:-3] + bytes([good_roster[-3] ^ 0xFF]) + good_roster[-2:],
        "deep json": b"[" * 100_000,
    }
    for case, data in rosters.items():
        (d / ROSTER).write_bytes(data)
        line = strict_one_line(keygen_cli, ["list", "--dir", str(d)])
        assert "roster" in line, (case, line)
    (d / ROSTER).unlink()
    assert "roster" in strict_one_line(keygen_cli, ["list", "--dir", str(d)])
    (d / ROSTER).mkdir()
    assert "roster" in strict_one_line(keygen_cli, ["list", "--dir", str(d)])


# -- Zenoh JSON5 configs -----------------------------------------------------------------------------
def bad_configs(d: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, what its one line must say)."""
    d.mkdir(exist_ok=True)
    present = d / "present.pem"
    present.write_text("not really a certificate\n")
    unreadable = d / "unreadable.pem"
    unreadable.write_text("x")
    unreadable.chmod(0)
    cases: dict[str, tuple[bytes, str]] = {
        "deep arrays": (b"{ a: " + b"[" * 5_000 + b"]" * 5_000 + b" }", "deeper than"),
        "deep objects": (b"{a:" * 200 + b"1" + b"}" * 200, "deeper than"),
        "deep with comments": (
            b"// [ [ [\n{ /* { */ x: '[[', y: " + b"[" * 40 + b"]" * 40 + b"}",
            "deeper than",
        ),
        "huge": (b"{ id: '" + b"a" * 1_100_000 + b"' }", "limit"),
        "binary": (bytes(range(256)) * 8, "UTF-8"),
    }
    for field in (
        "root_ca_certificate",
        "connect_certificate",
        "connect_private_key",
        "listen_certificate",
        "listen_private_key",
    ):
        body = f'transport: {{ link: {{ tls: {{ {field}: "{d / "missing" / field}.pem" }} }} }}'
        cases[f"missing {field}"] = (f"{{ {body} }}".encode(), field)
    if os.geteuid() != 0:  # root reads a mode-000 file
        cases["unreadable root_ca_certificate"] = (
            f'{{ transport: {{ link: {{ tls: {{ root_ca_certificate: "{unreadable}" }} }} }} }}'.encode(),
            "root_ca_certificate",
        )
    cases["directory as certificate"] = (
        f'{{ transport: {{ link: {{ tls: {{ connect_certificate: "{d}" }} }} }} }}'.encode(),
        "is not a file",
    )
    cases["missing password dictionary"] = (
        f'{{ transport: {{ auth: {{ usrpwd: {{ user: "a", password: "b", dictionary_file: "{d}/none.txt" }} }} }} }}'.encode(),
        "dictionary_file",
    )
    out = {}
    for i, (name, (data, says)) in enumerate(cases.items()):
        path = d / f"config-{i}.json5"
        path.write_bytes(data)
        out[name] = (path, says)
    return out


def test_every_bad_zenoh_config_is_one_line_exit_2_naming_why(tmp_path) -> None:
    from agent import agent_cli
    from groundstation import gcs_cli, ops
    from tools import record_cli, replay_cli

    rec = tmp_path / "rec.mcap"
    write_recording(rec)
    configs = bad_configs(tmp_path / "configs")
    subcommands = {
        "agent": (agent_cli.cli, ["--id", "1", "--duration-s", "1"]),
        "agent --ids": (agent_cli.cli, ["--ids", "1-2", "--duration-s", "1"]),
        "gcs": (gcs_cli.cli, ["--port", "0"]),
        "cmd": (ops.cmd_cli, ["hold", "--to", "1", "--timeout-s", "0.5"]),
        "status": (ops.status_cli, ["--listen-s", "0.1"]),
        "record": (record_cli.record_cli, ["-o", str(tmp_path / "r.mcap"), "--duration-s", "1"]),
        "replay": (replay_cli.replay_cli, [str(rec), "--speed", "inf"]),
    }
    for name, (fn, base) in subcommands.items():
        for case, (path, says) in configs.items():
            mode = ["--mesh-mode", "client"] if "certificate" in case else []
            line = strict_one_line(fn, [*base, *mode, "--zenoh-config", str(path)])
            assert says in line, (name, case, line)


def test_a_deep_zenoh_config_that_crashed_zenoh_is_refused_by_the_real_cli(tmp_path) -> None:
    """Before: Zenoh's parser overflowed its stack on this 100 KB file (exit 139, SIGSEGV)."""
    deep = tmp_path / "deep.json5"
    deep.write_text("{a:" + "[" * 50_000 + "]" * 50_000 + "}")
    for argv in (
        ["agent", "--id", "1", "--duration-s", "1"],
        ["record", "-o", tmp_path / "r.mcap", "--duration-s", "1"],
    ):
        done = covey(*argv, "--zenoh-config", deep)
        lines = text_lines(done.stderr)
        assert done.returncode == 2, (argv, done.returncode, done.stderr[-500:])
        assert len(lines) == 1 and "nests deeper than" in lines[0], done.stderr
        assert "Traceback" not in done.stderr


# -- npz weights -------------------------------------------------------------------------------------
def npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=True)
    return buf.getvalue()


def declared_npy(shape: tuple[int, ...], dtype: str = "<f4") -> bytes:
    """A .npy header that declares `shape` followed by a few bytes: what a 6 GB array costs an
    attacker in a zip (little)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return buf.getvalue() + b"\0" * 1024


def write_npz(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name + ".npy", data)
    return path


def bad_weights(d: Path) -> dict[str, tuple[Path, str]]:
    d.mkdir(exist_ok=True)
    with np.load(WEIGHTS) as z:
        good = {k: npy(z[k]) for k in z.files}
    cases: dict[str, tuple[dict[str, bytes] | bytes, str]] = {}
    for key in ("config", "lstm.weight_ih", "lstm.weight_hh", "lstm.bias", "head.0.weight"):
        cases[f"no {key}"] = ({k: v for k, v in good.items() if k != key}, key)
    cases["no head.1.bias"] = ({k: v for k, v in good.items() if k != "head.1.bias"}, "head.1")
    cases["6 GB weight_hh"] = (
        {**good, "lstm.weight_hh": declared_npy((25_000_000, 63))},
        "lstm.weight_hh",
    )
    cases["1-D weight_hh"] = ({**good, "lstm.weight_hh": npy(np.zeros(63, "f4"))}, "2-D")
    cases["int weights"] = ({**good, "head.0.weight": npy(np.zeros((64, 65), "i4"))}, "float")
    cases["object array"] = (
        {**good, "lstm.bias": npy(np.array([{"x": 1}], dtype=object))},
        "pickle",
    )
    cases["wrong shapes"] = ({**good, "lstm.weight_hh": npy(np.zeros((4, 3), "f4"))}, "shapes")
    cases["config not JSON"] = ({**good, "config": npy(np.array("{not json"))}, "not JSON")
    cases["config deep"] = ({**good, "config": npy(np.array("[" * 50_000))}, "deeper than")
    cases["config a list"] = ({**good, "config": npy(np.array("[1, 2]"))}, "JSON object")
    cases["config an array"] = ({**good, "config": npy(np.zeros(3, "f4"))}, "config")
    cases["torn member"] = ({**good, "lstm.bias": good["lstm.bias"][:60]}, "lstm.bias")
    cases["not a zip"] = (b"\x93NUMPY" + b"\0" * 200, "not an npz")
    cases["text"] = (b"hello", "not an npz")
    cases["empty"] = (b"", "not an npz")
    cases["a .npy"] = (npy(np.zeros(3, "f4")), "not an npz")
    raw = WEIGHTS.read_bytes()
    cases["truncated zip"] = (raw[: len(raw) // 2], "weights")
    out = {}
    for i, (name, (content, says)) in enumerate(cases.items()):
        path = d / f"w{i}.npz"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            write_npz(path, content)
        out[name] = (path, says)
    return out


def test_every_bad_weights_file_is_one_line_exit_2_before_loading(tmp_path) -> None:
    """Before: a missing key was a KeyError traceback, and a 5.9 MB file declaring a 6 GB
    array took 5.9 GB of memory for 27 s before its traceback."""
    import resource

    from agent import agent_cli
    from policy.runtime import GuidancePolicy

    rss_before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    cases = bad_weights(tmp_path)
    for case, (path, says) in cases.items():
        with pytest.raises(ValueError) as exc:
            GuidancePolicy.load(path)
        assert says in str(exc.value) and "\n" not in str(exc.value), (case, str(exc.value))
    for case in ("no lstm.bias", "6 GB weight_hh", "object array", "not a zip"):  # the agent's
        path, says = cases[case]  # CLI joins the mesh first: each costs a session
        line = strict_one_line(
            agent_cli.cli, ["--id", "1", "--policy", str(path), "--listen", "tcp/127.0.0.1:0"]
        )
        assert says in line, (case, line)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before_kb) / 1024
    assert grown_mb < 500, f"peak memory grew {grown_mb:.0f} MB"
    GuidancePolicy.load(WEIGHTS)  # the shipped weights still load


# -- MCAP recordings ---------------------------------------------------------------------------------
def write_recording(path: Path, n_states: int = 300) -> int:
    """A recording of 3 vehicles' states and a few events, in small chunks; its message count."""
    with open(path, "wb") as out:
        sink = McapSink(out, "fz", chunk_bytes=1024, flush_interval_s=60.0, foxglove=None)
        t0 = 1_700_000_000_000_000_000
        for i in range(n_states):
            vid = 1 + i % 3
            s = VehicleState(vid, i, t0 + i * 10**7, (float(i % 7), 0.0, -2.0), (0, 0, 0), 0.0)
            sink.put(f"covey/fz/c/0/0/v/{vid}/state", s.encode(), t0 + i * 10**7)
            if i % 100 == 0:
                e = Event(vid, t0 + i * 10**7, "hello")
                sink.put(f"covey/fz/msg/{vid}/event", e.encode(), t0 + i * 10**7)
        sink.close()
    return n_states + (n_states + 99) // 100


def run_cli(fn, argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = fn(argv)
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def test_cut_off_and_corrupted_recordings_are_used_as_far_as_they_read_and_said(tmp_path) -> None:
    """Before: `covey record --foxglove-from` copied what it could of a cut-off or corrupted
    recording and exited 0, without a word."""
    from tools.record_cli import record_cli

    src = tmp_path / "good.mcap"
    total = write_recording(src)
    raw = src.read_bytes()
    data_end = raw.rfind(b"\x0f" + (4).to_bytes(8, "little"))  # DataEnd: opcode 0x0F, length 4
    assert data_end > 0
    code, _, err = run_cli(record_cli, ["--foxglove-from", str(src), "-o", str(tmp_path / "o")])
    assert code == 0 and not text_lines(err), err
    whole = [(m.topic, m.data) for m in read_recording(src).messages]
    rng = random.Random(SEED + 5)
    bad = tmp_path / "bad.mcap"
    outcomes = {"partial": 0, "refused": 0, "whole": 0}
    cuts = sorted({rng.randrange(0, data_end) for _ in range(40)} | {0, 5, 8, 30, data_end - 1})
    flips = sorted({rng.randrange(8, data_end) for _ in range(40)})
    for kind, offsets in (("cut", cuts), ("flip", flips)):
        for off in offsets:
            if kind == "cut":
                bad.write_bytes(raw[:off])
            else:
                bad.write_bytes(raw[:off] + bytes([raw[off] ^ 0x5A]) + raw[off + 1 :])
            code, _, err = run_cli(
                record_cli, ["--foxglove-from", str(bad), "-o", str(tmp_path / "out.mcap")]
            )
            lines = text_lines(err)
            assert "Traceback" not in err, (kind, off, err)
            if code == PARTIAL_EXIT:
                assert len(lines) == 1 and "incomplete" in lines[0], (kind, off, err)
                kept = int(re.search(r"kept (\d+) messages", lines[0]).group(1))
                assert 0 < kept <= total, (kind, off, lines[0])  # <=: only the summary lost
                assert len(read_recording(tmp_path / "out.mcap").messages) == kept
                outcomes["partial"] += 1
            elif code == 2:
                assert len(lines) == 1, (kind, off, err)
                outcomes["refused"] += 1
            else:  # a flip outside the data (an index, a time range): every message is whole
                assert kind == "flip" and code == 0 and not lines, (kind, off, code, err)
                copied = read_recording(tmp_path / "out.mcap").messages
                assert [(m.topic, m.data) for m in copied] == whole, (kind, off)
                outcomes["whole"] += 1
    print(f"{len(cuts)} cuts, {len(flips)} flipped bytes: {outcomes}")
    assert outcomes["partial"] >= len(cuts) // 2  # every cut past the first chunk
    assert outcomes["partial"] + outcomes["refused"] >= len(flips) // 4 + len(cuts)
    not_mcap = tmp_path / "not.mcap"
    not_mcap.write_bytes(b"hello world" * 10)
    for argv in (
        ["--foxglove-from", str(not_mcap), "-o", str(tmp_path / "x")],
        ["--info", str(not_mcap)],
    ):
        code, _, err = run_cli(record_cli, argv)
        assert code == 2 and len(text_lines(err)) == 1 and "not an MCAP" in err, (argv, err)


def test_replay_of_a_cut_off_recording_replays_what_is_there_warns_and_exits_1(tmp_path) -> None:
    from tools.replay_cli import replay_cli

    src = tmp_path / "good.mcap"
    write_recording(src)
    raw = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) // 2])
    into = ["--mesh-mode", "router", "--listen", f"tcp/127.0.0.1:{free_tcp_port()}"]
    code, out, err = run_cli(
        replay_cli, [str(cut), "--speed", "inf", "--presence-wait-s", "0", *into]
    )
    assert code == PARTIAL_EXIT, (code, out, err)
    warning = [ln for ln in text_lines(err) if "incomplete" in ln]
    assert len(warning) == 1 and "kept" in warning[0], err
    replayed = int(re.search(r"replayed (\d+) states", out).group(1))
    assert 0 < replayed < 300, out
    for junk in (b"", b"\x89MCAP0\r\n", b"not an mcap file"):
        cut.write_bytes(junk)
        line = strict_one_line(replay_cli, [str(cut), "--speed", "inf", *into])
        assert "MCAP" in line or "no covey messages" in line, line


# -- waiting for nobody --------------------------------------------------------------------------------
def test_tools_that_find_nobody_say_where_they_looked_and_exit_1(tmp_path) -> None:
    """Before: "no vehicles on the mesh", "no vehicle answered", "replayed 973 states", exit 0."""
    from groundstation import ops
    from tools.replay_cli import replay_cli

    rec = tmp_path / "rec.mcap"
    write_recording(rec, n_states=30)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"  # nothing listens there
    for fn, argv in (
        (ops.status_cli, ["--listen-s", "0.3"]),
        (ops.status_cli, ["--listen-s", "0.3", "--mesh-mode", "client"]),
        (ops.cmd_cli, ["hold", "--to", "all", "--timeout-s", "0.3"]),
        (ops.cmd_cli, ["land", "--to", "1", "--timeout-s", "0.3", "--mesh-mode", "client"]),
        (replay_cli, [str(rec), "--speed", "inf", "--presence-wait-s", "0"]),
    ):
        code, out, err = run_cli(fn, [*argv, "--connect", endpoint])
        said = [ln for ln in text_lines(err) if "answered" in ln]  # replay also says "replaying"
        assert code == 1, (argv, code, out, err)
        assert len(said) == 1 and endpoint in said[0] and "error" not in said[0], (argv, err)
        assert "replayed" not in out and "no vehicle" not in out, out


@pytest.mark.e2e
def test_a_client_waiting_for_its_router_ends_on_sigterm_and_record_on_its_duration(
    tmp_path,
) -> None:
    """Before: `covey agent --mesh-mode client` was alive 5 s after SIGTERM, and `covey record
    --duration-s 12` waited 10 minutes for its router."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    agent = subprocess.Popen(
        [sys.executable, "-m", "covey_cli", "agent", "--id", "1", "--mesh-mode", "client"]
        + ["--connect", endpoint],
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    t0 = time.monotonic()
    recorder = covey(
        "record", "-o", tmp_path / "r.mcap", "--duration-s", "2", "--connect", endpoint
    )
    record_s = time.monotonic() - t0
    assert agent.poll() is None, "the agent did not wait for its router"
    agent.send_signal(signal.SIGTERM)
    try:
        _, agent_err = agent.communicate(timeout=5)
    except subprocess.TimeoutExpired:
        agent.kill()
        pytest.fail("the agent was still waiting for its router 5 s after SIGTERM")
    lines = text_lines(agent_err)
    assert agent.returncode == 2 and "Traceback" not in agent_err, agent_err
    assert len(lines) == 1 and f"no router answered at {endpoint}" in lines[0], agent_err
    lines = text_lines(recorder.stderr)
    assert recorder.returncode == 1, recorder.stderr
    assert f"no router answered at {endpoint}" in lines[-1], recorder.stderr
    assert record_s < 15, f"covey record --duration-s 2 ran {record_s:.1f} s"
