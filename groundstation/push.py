"""Publish a signed fleet document (the roster, the fleet plan) and count who confirmed it.

    heard = push_and_confirm(cfg, duration_s, publish, confirm)   # the confirmations, or []

The one push loop behind `covey keygen push` and `covey plan push`: join the mesh (a client
waits at most PUSH_LINK_WAIT_S for its router and says nobody answered), put the document
again and again until a member confirms or `duration_s` ends (members may still be joining),
then ask once more, so that members still applying it count too. Each confirmation names its
replier and the version it holds (trust/roster_sync.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from cli.options import stop_on_signals
from comms.session import MeshConfig

PUSH_LINK_WAIT_S = 3.0
"""How long a push waits for a router or peer to answer before saying nobody did."""
CONFIRM_TIMEOUT_S = 0.5
"""How long one round of confirmation queries waits for answers."""


def push_and_confirm(
    cfg: MeshConfig,
    duration_s: float,
    publish: Callable[[Any], None],
    confirm: Callable[[Any, float], list],
) -> list:
    """Confirmations of the pushed document (an empty list: nobody confirmed in `duration_s`).
    `publish(mesh)` puts the document; `confirm(session, timeout_s)` asks the members.
    Raises comms.session.MeshUnreachable when a client's router never answers."""
    from comms.mesh import Mesh
    from comms.session import expects_answer, unreachable, wait_linked

    wait_s = max(duration_s, PUSH_LINK_WAIT_S)
    heard: list = []
    with stop_on_signals() as stop, Mesh(cfg, stop=stop, wait_s=wait_s) as mesh:
        if expects_answer(cfg) and not wait_linked(mesh.session, wait_s, stop):
            raise unreachable(cfg, wait_s)  # a push into nothing is not "pushed"
        deadline = time.monotonic() + duration_s
        while not stop.is_set():  # re-put: members may still be connecting
            publish(mesh)
            heard = confirm(mesh.session, CONFIRM_TIMEOUT_S)
            if heard or time.monotonic() >= deadline:
                break
            stop.wait(0.25)
        if heard:  # one more round: members still applying it count too
            stop.wait(0.5)
            heard += confirm(mesh.session, CONFIRM_TIMEOUT_S)
    return heard
