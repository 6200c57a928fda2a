"""What keyed mode costs: signature µs, agent CPU at 10 neighbours, command-to-all-acks latency.

    python -m bench.trust [--quick]          # writes trust.json (also a `python -m bench` section)

- crypto: Ed25519 sign and verify of one state (`cryptography`, process CPU time), and the
  whole receive path per state: decode alone (open mode) vs decode + Gate (keyed).
- agent CPU: bench/agent_cpu.py's real `covey agent` flying a goto with 10 neighbours at 10 Hz,
  open vs keyed (the neighbours sign with their own keys, the agent verifies them), alternated
  so that both see the same machine load.
- commands: one broadcast to n vehicles (10, 100) served by two child processes, time until
  every ack is in at the station: open vs keyed (station-signed command, n Ed25519 verifications
  on the vehicles' side, n signed acks verified by the station).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time

from bench import agent_cpu, common
from comms.session import embedded_peer, embedded_router, free_tcp_port

FLEET = "benchtrust"


def crypto(n: int) -> dict:
    from comms.gate import Gate
    from comms.schema import Mode, Role, VehicleState
    from trust.auth import load_auth
    from trust.authority import throwaway_fleet

    with tempfile.TemporaryDirectory() as d:
        fleet = throwaway_fleet(d, FLEET, vehicles=[1, 2, *range(10, 29)], stations=[1])
        v1 = load_auth(str(fleet.member_path(Role.VEHICLE, 1)))
        receiver = load_auth(str(fleet.member_path(Role.VEHICLE, 2)))
    now = time.time_ns()
    states = [
        VehicleState(1, i, now + i, (1.0, 2.0, -10.0), (1.0, 0.0, 0.0), 0.1, Mode.GOTO, True)
        for i in range(n)
    ]
    t0 = time.process_time()
    signed = [v1.sign_state(s) for s in states]
    t1 = time.process_time()
    for s in signed:
        receiver.check_state(s)
    t2 = time.process_time()
    open_bytes = [s.encode() for s in states]
    keyed_bytes = [s.encode() for s in signed]
    t3 = time.process_time()
    for b in open_bytes:
        VehicleState.decode(b)
    t4 = time.process_time()
    gate = Gate(receiver)
    for b in keyed_bytes:
        gate.admit_state(VehicleState.decode(b), now + n)
    t5 = time.process_time()
    assert gate.accepted == n, gate.refused
    # the same states tagged for 20 receivers, the receiver among them (trust/links.py)
    receivers = [2, *range(10, 29)]
    t6 = time.process_time()
    tagged = [v1.sign_state(s, receivers) for s in states]
    t7 = time.process_time()
    for s in tagged:
        assert receiver.check_state(s) is None
    t8 = time.process_time()
    tagged_bytes = [s.encode() for s in tagged]
    gate = Gate(receiver)
    t9 = time.process_time()
    for b in tagged_bytes:
        gate.admit_state(VehicleState.decode(b), now + n)
    t10 = time.process_time()
    assert gate.accepted == n, gate.refused
    us = lambda dt: dt * 1e6 / n  # noqa: E731
    return {
        "states": n,
        "sign_us": us(t1 - t0),
        "verify_us": us(t2 - t1),
        "open_receive_us": us(t4 - t3),
        "keyed_receive_us": us(t5 - t4),
        "state_bytes_open": len(open_bytes[0]),
        "state_bytes_keyed": len(keyed_bytes[0]),
        "sign_and_tag_20_us": us(t7 - t6),
        "link_check_us": us(t8 - t7),
        "tagged_receive_us": us(t10 - t9),
        "state_bytes_tagged_20": len(tagged_bytes[0]),
    }


def agent(quick: bool, pairs: int) -> dict:
    from trust.authority import throwaway_fleet

    runs: dict[str, list[dict]] = {"open": [], "keyed": []}
    with tempfile.TemporaryDirectory() as d:
        throwaway_fleet(
            d,
            agent_cpu.FLEET,
            vehicles=[agent_cpu.AGENT_ID, *agent_cpu.neighbour_ids()],
            stations=[1],
        )
        for _ in range(pairs):
            for kind, keys_dir in (("open", None), ("keyed", d)):
                r = agent_cpu.agent_flight(quick, keys_dir=keys_dir)
                runs[kind].append(r["flying"])
                common.say(
                    f"agent {kind}: {100 * r['flying']['cpu_share_of_one_core']:.2f} % of a core, "
                    f"jitter p99 {r['flying']['tick_jitter_ms_p99']:.2f} ms"
                )
    mean = {k: sum(r["cpu_share_of_one_core"] for r in v) / len(v) for k, v in runs.items()}
    return {
        "runs": runs,
        "cpu_share_open": mean["open"],
        "cpu_share_keyed": mean["keyed"],
        "ratio": mean["keyed"] / mean["open"],
    }


def role_resp(port: int, first: int, count: int, keys_dir: str | None) -> None:
    """Answer commands for `count` vehicles until killed (each with its own key when keyed)."""
    from comms.mesh import Mesh
    from comms.schema import AckResult, CommandAck, Mode, Role
    from trust.auth import load_auth

    auths: dict = {}
    mesh_auth = None
    if keys_dir is not None:
        from trust.authority import Authority

        fleet = Authority(keys_dir)
        auths = {
            v: load_auth(str(fleet.member_path(Role.VEHICLE, v)))
            for v in range(first, first + count)
        }
        mesh_auth = auths[first]
    with Mesh(embedded_peer(port, fleet=FLEET), auth=mesh_auth) as mesh:
        for v in range(first, first + count):
            mesh.serve_commands(
                v,
                lambda c, v=v: CommandAck(
                    v, c.nonce, mesh.clock_ns(), AckResult.ACCEPTED, "", Mode.LANDED
                ),
                auth=auths.get(v),
            )
            mesh.declare_vehicle(v)
        print("READY", flush=True)
        threading.Event().wait()


def commands(n: int, repeats: int, keys_dir: str | None) -> dict:
    from comms.commands import OutcomeStatus, new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command, CommandKind, Role
    from trust.auth import load_auth

    port = free_tcp_port()
    auth = None
    if keys_dir is not None:
        from trust.authority import Authority

        auth = load_auth(str(Authority(keys_dir).member_path(Role.STATION, 1)))
    ids = set(range(1, n + 1))
    all_ms, incomplete = [], 0
    with Mesh(embedded_router(port, fleet=FLEET), auth=auth) as mesh, common.children() as kids:
        pres = mesh.presence()
        half = (n + 1) // 2
        for first, count in ((1, half), (half + 1, n - half)):
            if count > 0:
                extra = ["--keys-dir", keys_dir] if keys_dir else []
                p = kids.start(
                    "-m",
                    "bench.trust",
                    "--role",
                    "resp",
                    "--port",
                    str(port),
                    "--first",
                    str(first),
                    "--count",
                    str(count),
                    *extra,
                )
                p.wait_for("READY", timeout_s=120)
        if not pres.wait_for(lambda v, _g: v >= ids, 90.0):
            raise RuntimeError(f"only {len(pres.vehicles)} of {n} vehicles present")
        time.sleep(1.0)
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = mesh.send_command(
                Command(CommandKind.LAND, new_nonce(), time.time_ns()), expect=ids, timeout_s=5.0
            )
            dt_s = time.perf_counter() - t0
            incomplete += len(res.by_status(OutcomeStatus.ACCEPTED)) < n
            all_ms.append(dt_s * 1e3)
            time.sleep(0.05)
    return {
        "vehicles": n,
        "repeats": repeats,
        "incomplete": incomplete,
        "all_acks_ms_p50": common.pct(all_ms, 50),
        "all_acks_ms_p99": common.pct(all_ms, 99),
    }


def main(quick: bool = False) -> dict:
    from trust.authority import throwaway_fleet

    c = crypto(500 if quick else 3000)
    common.say(
        f"Ed25519 per state: sign {c['sign_us']:.0f} us, verify {c['verify_us']:.0f} us; receive path "
        f"open {c['open_receive_us']:.0f} us vs keyed {c['keyed_receive_us']:.0f} us; state "
        f"{c['state_bytes_open']} -> {c['state_bytes_keyed']} bytes; link tags: a check "
        f"{c['link_check_us']:.1f} us, tagged receive path {c['tagged_receive_us']:.0f} us, sign "
        f"and tag for 20 {c['sign_and_tag_20_us']:.0f} us, {c['state_bytes_tagged_20']} bytes"
    )
    a = agent(quick, pairs=1 if quick else 2)
    common.say(
        f"agent at 10 neighbours, 10 Hz: open {100 * a['cpu_share_open']:.2f} % vs keyed "
        f"{100 * a['cpu_share_keyed']:.2f} % of a core ({a['ratio']:.2f}x)"
    )
    cmds = []
    with tempfile.TemporaryDirectory() as d:
        throwaway_fleet(d, FLEET, vehicles=range(1, 101), stations=[1])
        for n in (10, 100):
            for kind, keys_dir in (("open", None), ("keyed", d)):
                r = commands(n, 5 if quick else 20, keys_dir)
                r["kind"] = kind
                cmds.append(r)
                common.say(
                    f"command to all acks, {kind:5s} n={n:3d}: p50 {r['all_acks_ms_p50']:.1f} ms, "
                    f"p99 {r['all_acks_ms_p99']:.1f} ms, incomplete {r['incomplete']}"
                )
    return {"quick": quick, "crypto": c, "agent_cpu": a, "commands": cmds}


def cli(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--role", default="bench", choices=["bench", "resp"])
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--count", type=int, default=1)
    ap.add_argument("--keys-dir", default=None)
    a = ap.parse_args(argv)
    if a.role == "resp":
        role_resp(a.port, a.first, a.count, a.keys_dir)
        return
    result = main(a.quick)
    common.write_json("trust", result)
    print(
        json.dumps(
            {k: v for k, v in result.items() if k != "agent_cpu"}
            | {"agent_ratio": result["agent_cpu"]["ratio"]},
            indent=1,
        )
    )


if __name__ == "__main__":
    cli()
