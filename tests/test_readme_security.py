"""The README's security quickstart, run as written: so that the README cannot drift again.

The block after the README's `<!-- tests/test_readme_security.py runs the next block as
written -->` marker is run literally with bash (-e: any failing line fails the test), in a temp
HOME, from the repository root. Its ports (the router's 7447, the stations' web ports) are the
README's own, so the block runs in a private network namespace where one can be made (its own
loopback: nothing else on the machine is in the way); elsewhere it is skipped when 7447 is busy.

Checked after the block: it ended by itself (its last line stops what it started), both pushes
were confirmed by the running members, the vehicle applied the roster that revokes station 1 and
the station-1 process was told it is revoked, station 2 landed the vehicle, and no TLS or fleet key
was written into the repository.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MARKER = "<!-- tests/test_readme_security.py runs the next block as written -->"
TIMEOUT_S = 240


def security_block(readme: str) -> str:
    """The one fenced bash block right after the marker."""
    assert readme.count(MARKER) == 1, "the README must mark exactly one security block"
    after = readme.split(MARKER, 1)[1]
    m = re.match(r"\s*```bash\n(.*?)\n```", after, re.S)
    assert m, "the marker must be followed by a ```bash block"
    return m.group(1) + "\n"


def netns_prefix() -> list[str] | None:
    """`unshare` into a new network namespace with loopback up, if this machine allows it."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return None
    probe = subprocess.run(
        ["unshare", "-rn", "ip", "link", "set", "lo", "up"], capture_output=True, timeout=30
    )
    return ["unshare", "-rn"] if probe.returncode == 0 else None


def port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def repo_keys() -> set[Path]:
    skip = {".venv", ".git", "firmware", "node_modules"}
    found = set()
    for root, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in skip]
        found |= {Path(root) / f for f in files if f.endswith((".key", ".pem"))}
    return found


@pytest.mark.e2e
@pytest.mark.slow
def test_the_readme_security_quickstart_runs_as_written(tmp_path) -> None:
    if not (REPO / ".venv" / "bin" / "covey").exists():
        pytest.skip("no .venv/bin/covey (make demo installs it)")
    block = security_block((REPO / "README.md").read_text())
    script = tmp_path / "quickstart.sh"
    script.write_text(block)
    prefix = netns_prefix()
    if prefix is None and not port_free(7447):
        pytest.skip("port 7447 is busy and no private network namespace can be made")
    run = [*(prefix or []), "bash", "-c", 'ip link set lo up 2>/dev/null; exec bash -e "$0"']
    home = tmp_path / "home"
    home.mkdir()
    env = {
        "HOME": str(home),
        "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
        "LANG": "C.UTF-8",
        "OMP_WAIT_POLICY": "PASSIVE",
        "OPENBLAS_NUM_THREADS": "1",
    }
    keys_before = repo_keys()
    proc = subprocess.Popen(
        [*run, str(script)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = proc.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"the quickstart did not finish in {TIMEOUT_S} s:\n{out[-6000:]}")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # whatever a failed block left running
        except ProcessLookupError:
            pass
    print(out[-4000:])
    assert proc.returncode in (0, -signal.SIGTERM, 128 + signal.SIGTERM), out[-6000:]
    assert "Traceback" not in out, out[-6000:]
    pushes = re.findall(r"pushed fleet covey roster v(\d+) .*: (\d+) member\(s\) confirmed", out)
    assert len(pushes) == 2, out[-6000:]
    revoking = int(pushes[1][0])
    assert all(int(n) >= 1 for _, n in pushes), pushes
    # The agent (its log lines carry the logger's name) applied the roster that revokes station 1.
    assert re.search(rf"trust\.auth WARNING applied fleet roster v{revoking}\b", out), out[-6000:]
    assert re.search(rf"roster v{revoking} REVOKES this process's station 1", out), out[-6000:]
    land = out.split(f"pushed fleet covey roster v{revoking}", 1)[1]
    assert re.search(r"\b1\b.*accepted", land, re.I), land[-3000:]
    assert repo_keys() == keys_before, "a key or certificate was written into the repository"
    fleet = home / ".config" / "covey"
    assert (fleet / "tls" / "ca.key").stat().st_mode & 0o777 == 0o600
    assert not (fleet / "fleet" / "station-1.key").exists()  # revoked: its file went
