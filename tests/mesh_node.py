"""A small real mesh process for the comms tests: `python tests/mesh_node.py PORT ID BEHAVIOUR`.

It joins the embedded mesh as a peer, declares vehicle ID alive, publishes a VehicleState at
10 Hz and answers commands according to BEHAVIOUR: accept | reject | hang (never answers) |
echo-states (prints every state it receives as `STATE <id> <seq> <stamp_ns>` on stdout).
It prints READY once its queryable and token are declared.
"""

from __future__ import annotations

import sys
import threading
import time

from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandAck, Mode, VehicleState
from comms.session import embedded_peer


def main(port: int, vid: int, behaviour: str, fleet: str = "covey") -> None:
    stop = threading.Event()

    def handler(cmd: Command) -> CommandAck:
        if behaviour == "hang":
            stop.wait(30)
        result = AckResult.REJECTED if behaviour == "reject" else AckResult.ACCEPTED
        reason = f"vehicle {vid} says no" if behaviour == "reject" else ""
        return CommandAck(vid, cmd.nonce, time.time_ns(), result, reason, Mode.HOLDING)

    with Mesh(embedded_peer(port, fleet=fleet)) as mesh:
        mesh.serve_commands(vid, handler)
        if behaviour == "echo-states":
            mesh.subscribe_states(
                lambda s, t: print(f"STATE {s.vehicle_id} {s.seq} {s.stamp_ns} {t}", flush=True)
            )
        mesh.declare_vehicle(vid)
        print("READY", flush=True)
        seq = 0
        while not stop.is_set():
            seq += 1
            mesh.publish_state(
                VehicleState(
                    vid, seq, time.time_ns(), (float(vid), 0.0, -10.0), (0.0, 0.0, 0.0), 0.0
                )
            )
            stop.wait(0.1)


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], *(sys.argv[4:5]))
