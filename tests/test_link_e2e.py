"""The xbee link between a real agent process and a receiver, over a real Zenoh mesh."""

from __future__ import annotations

import sys
import threading
import time
import uuid

import pytest

from comms.link import emulator_from_spec
from comms.mesh import Mesh
from comms.session import embedded_router, free_tcp_port
from kit.procs import Child

pytestmark = pytest.mark.e2e


def test_xbee_link_thins_delays_and_counts_a_live_stream():
    fleet = "lk" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    offered: list[int] = []
    delivered: list[tuple[int, int, int]] = []  # (seq, wire recv_ns, delivery ns)
    recv_by_seq: dict[int, int] = {}
    lock = threading.Lock()
    with (
        Mesh(embedded_router(port, fleet=fleet)) as mesh,
        emulator_from_spec("xbee", seed=4) as link,
    ):

        class Tap:  # records what the wire offered, then hands it to the link
            def offer(self, state, recv_ns, deliver):
                with lock:
                    offered.append(recv_ns)
                    recv_by_seq[state.seq] = recv_ns
                link.offer(state, recv_ns, deliver)

        def on_state(state, t_ns):
            with lock:
                delivered.append((state.seq, recv_by_seq[state.seq], t_ns))

        mesh.subscribe_states(on_state, link=Tap())
        agent = [
            sys.executable,
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "5",
            "--fleet",
            fleet,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--no-gcs-failsafe",
            "--idle-state-hz",  # a live 10 Hz stream for the link, landed as it is
            "10",
        ]
        with Child(agent, output="discard", stderr="discard", grace_s=10.0):
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                with lock:
                    if len(offered) >= 60:
                        break
                time.sleep(0.1)
        time.sleep(0.3)  # let the last delayed states out
        stats = link.stats()[5]
    with lock:
        assert len(offered) >= 60
        assert stats.offered == len(offered)
        assert stats.delivered == len(delivered)
        assert stats.delivered + sum(stats.dropped.values()) == stats.offered
        # The rate gate lets at most one state through per 1/3 s slot of the stream.
        span_s = (offered[-1] - offered[0]) / 1e9
        assert stats.transmitted <= span_s * 3.0 + 1
        if len(offered) / span_s > 3.5:  # a stream faster than the link must be thinned
            assert stats.dropped["rate"] > 0
        for _seq, recv_ns, at_ns in delivered:
            assert 0.07 - 1e-9 <= (at_ns - recv_ns) / 1e9 <= 0.13 + 1e-9
        seqs = [s for s, _, _ in delivered]
        assert seqs == sorted(seqs)
