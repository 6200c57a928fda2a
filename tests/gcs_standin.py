"""A ground-station stand-in process for tests: joins the mesh and holds a station's liveliness
token until it is killed. `python tests/gcs_standin.py PORT [FLEET]`"""

from __future__ import annotations

import sys
import threading

from comms.mesh import Mesh
from comms.session import embedded_peer

if __name__ == "__main__":
    with Mesh(
        embedded_peer(int(sys.argv[1]), fleet=sys.argv[2] if len(sys.argv) > 2 else "covey")
    ) as mesh:
        mesh.declare_gcs(1)
        print("READY", flush=True)
        threading.Event().wait()
