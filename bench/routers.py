"""What a multi-site layout costs: state latency and command round trips across Zenoh routers.

    python -m bench.routers [--quick]      # writes routers.json

Every role is its own process on loopback, with bench/mesh.py's roles (n vehicles publishing
covey states at 10 Hz from one process, or answering commands; a hub that measures stamp ->
receive latency, or the time from a broadcast command to every ack):
- direct: the hub hosts the embedded router and the vehicles' process is its peer (covey's
  default single-site layout);
- 1 router: one `covey router`; hub and vehicles are its clients;
- 3 routers: `covey router` R1 <-> R2 <-> R3 in a chain; the hub is a client of R1 and the
  vehicles of R3, so every state crosses three routers and two router-to-router links.
"""

from __future__ import annotations

import argparse
import json

from bench import common
from comms.session import free_tcp_port

VEHICLES = 20
LAYOUTS = ("direct", "1 router", "3 routers")


def _routers(kids, count: int) -> list[str]:
    """Start `count` `covey router`s in a chain; their endpoints, R1 first."""
    started = common.start_routers(kids, count, chain=True)
    if count > 2:
        started[1][0].wait_for("covey router: 2 router(s)", timeout_s=60)
    return [f"tcp/127.0.0.1:{port}" for _, port in started]


def run_one(layout: str, what: str, n: int, window_s: float, repeats: int) -> dict:
    with common.children() as kids:
        if layout == "direct":
            port = str(free_tcp_port())
            hub_mesh = member_mesh = ["--port", port]
        else:
            eps = _routers(kids, 1 if layout == "1 router" else 3)
            hub_mesh, member_mesh = ["--connect", eps[0]], ["--connect", eps[-1]]
        role = ["-m", "bench.mesh", "--kind", "covey", "--count", str(n)]
        hub = kids.start(
            *role,
            "--role",
            f"hub-{what}",
            "--window-s",
            str(window_s),
            "--repeats",
            str(repeats),
            *hub_mesh,
        )
        hub.wait_for("READY", timeout_s=60)
        member = kids.start(*role, "--role", "pub" if what == "states" else "resp", *member_mesh)
        member.wait_for("READY", timeout_s=60)
        res = json.loads(hub.wait_for("RESULT", timeout_s=180).removeprefix("RESULT"))
    res["layout"] = layout
    return res


def main(quick: bool = False) -> dict:
    window_s, repeats = (3.0, 5) if quick else (8.0, 30)
    states, cmds = [], []
    for layout in LAYOUTS:
        r = run_one(layout, "states", VEHICLES, window_s, repeats)
        states.append(r)
        common.say(
            f"states  {layout:9s}: p50 {r.get('latency_ms_p50', float('nan')):6.2f} ms, "
            f"p99 {r.get('latency_ms_p99', float('nan')):6.2f} ms, "
            f"delivered {r.get('delivered_share', 0):.3f} of 10 Hz, "
            f"lost {r.get('lost_share', float('nan')):.4f} of those sent"
        )
    for layout in LAYOUTS:
        r = run_one(layout, "cmds", VEHICLES, window_s, repeats)
        cmds.append(r)
        common.say(
            f"command {layout:9s}: all {VEHICLES} acks p50 "
            f"{r.get('all_acks_ms_p50', float('nan')):6.2f} ms, "
            f"p99 {r.get('all_acks_ms_p99', float('nan')):6.2f} ms"
        )
    result = {"quick": quick, "vehicles": VEHICLES, "states": states, "commands": cmds}
    common.write_json("routers", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    main(ap.parse_args().quick)
