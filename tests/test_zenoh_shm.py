"""`covey agent` turns Zenoh's shared-memory transport off (comms/session.py
MeshConfig.shared_memory): it carries nothing for an agent, and a link between two processes on
one host that negotiates it starts a watchdog thread in each, waking 20 times a second."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest
import zenoh

from comms.session import MeshConfig, embedded_router, free_tcp_port

SHM = "transport/shared_memory/enabled"
CHILD = """
import os, sys, time, zenoh
from comms.session import MeshConfig
on = sys.argv[2] == "on"
cfg = MeshConfig(fleet="shm", mode="client", connect=(sys.argv[1],), shared_memory=on)
with zenoh.open(cfg.zenoh_config()) as s:
    sub = s.declare_subscriber("shm/**")
    s.put("shm/hello", b"x")
    time.sleep(1.5)
    names = [open(f"/proc/self/task/{{t}}/comm").read().strip() for t in os.listdir("/proc/self/task")]
    print("THREADS " + "|".join(sorted(names)), flush=True)
"""


def test_the_config_sets_it_only_when_asked(tmp_path) -> None:
    path = tmp_path / "shm.json5"
    path.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert MeshConfig(config_file=str(path)).zenoh_config().get_json(SHM) == "true"
    off = MeshConfig(config_file=str(path), shared_memory=False)
    assert off.zenoh_config().get_json(SHM) == "false", "the field wins over the file"
    assert MeshConfig(shared_memory=True).zenoh_config().get_json(SHM) == "true"


def test_covey_agent_turns_it_off() -> None:
    from agent.agent_cli import config_from_args, parser

    p = parser()
    cfg = config_from_args(p.parse_args(["--id", "3", "--fleet", "shm"]), p)
    assert cfg.mesh.shared_memory is False
    assert cfg.mesh.zenoh_config().get_json(SHM) == "false"


def _threads(endpoint: str, shm: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD.format(shm=SHM), endpoint, shm],
        capture_output=True,
        text=True,
        timeout=60,
    )
    line = [x for x in out.stdout.splitlines() if x.startswith("THREADS ")]
    assert line, out.stderr[-2000:]
    return line[0].removeprefix("THREADS ").split("|")


@pytest.mark.e2e
def test_an_agents_session_starts_no_shared_memory_watchdog() -> None:
    port = free_tcp_port()
    router = embedded_router(port, fleet="shm")
    router = type(router)(**{**router.__dict__, "extra": ((SHM, "true"),)})  # the router offers it
    with zenoh.open(router.zenoh_config()) as session:
        stop = threading.Event()
        talker = threading.Thread(target=_talk, args=(session, stop), daemon=True)
        talker.start()
        try:
            offered = _threads(f"tcp/127.0.0.1:{port}", "on")
            ours = _threads(f"tcp/127.0.0.1:{port}", "off")
        finally:
            stop.set()
            talker.join(5)
    if not any(n.startswith("Watchdog") for n in offered):
        pytest.skip(f"no shared-memory link on this machine (threads: {offered})")
    assert not any(n.startswith("Watchdog") for n in ours), ours


def _talk(session, stop) -> None:
    """A relay batch's worth (4 KiB, above Zenoh's 3 KB threshold for putting a message in
    shared memory) for the child to hear, as an agent hears its cell relay's."""
    while not stop.wait(0.05):
        session.put("shm/batch", bytes(4000))
