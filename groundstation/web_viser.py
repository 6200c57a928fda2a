"""viser, behind the login gate: its server on an internal loopback port that answers only
requests carrying the gate's secret, with its public share tunnel switched off.

viser has no login and checks no Origin, and its `websockets` server is built inside
`WebsockServer._background_worker`, with no hook to add either. So the station runs viser on
127.0.0.1 at a free port, and groundstation.web_proxy (the gate) is the only door to it: every
request it passes on carries `X-Covey-Proxy: <secret>` (made at start, never sent to a browser).
The check on viser's side is installed by wrapping `websockets.asyncio.server.serve` for the
moment viser starts (only for viser's own handler; any other server passes through untouched),
and the station refuses to start if viser did not start through the wrapper. A page or a process
that finds the internal port gets 403 and nothing else.

`operator_of` reads the operator that the gate put in a websocket's upgrade request, so that
every command a tab sends names who was logged in.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import io
import threading
from collections.abc import Iterator

import viser
import websockets.asyncio.server

from groundstation.web_auth import OPERATOR_HEADER, PROXY_HEADER

_SERVE_LOCK = threading.Lock()
"""One guarded viser start at a time (the wrapper is process-wide while it is installed)."""
_VISER_HANDLER_MODULE = "viser.infra._infra"


class _Viser(viser.ViserServer):
    """viser without its share tunnel: a ShareUrlRequest from any tab would otherwise open a
    public URL (share.viser.studio) to the internal port."""

    def request_share_url(self, verbose: bool = True) -> str | None:  # noqa: ARG002 - viser's signature
        return None


@contextlib.contextmanager
def _guarded_serve(secret: str, used: threading.Event) -> Iterator[None]:
    real = websockets.asyncio.server.serve

    def serve(handler, *args, process_request=None, **kwargs):  # noqa: ANN001 - websockets' own
        if getattr(handler, "__module__", "") != _VISER_HANDLER_MODULE:
            return real(handler, *args, process_request=process_request, **kwargs)

        def check(connection, request):  # noqa: ANN001
            got = request.headers.get(PROXY_HEADER, "")
            if not hmac.compare_digest(got.encode(), secret.encode()):
                return connection.respond(
                    http.HTTPStatus.FORBIDDEN, "covey: use the station's login port\n"
                )
            return process_request(connection, request) if process_request else None

        used.set()
        return real(handler, *args, process_request=check, **kwargs)

    with _SERVE_LOCK:
        # websockets types `serve` as a class; for this block it is a function that wraps it
        websockets.asyncio.server.serve = serve  # type: ignore[misc, assignment]
        try:
            yield
        finally:
            websockets.asyncio.server.serve = real  # type: ignore[misc]


def start_viser(secret: str, label: str = "covey") -> viser.ViserServer:
    """A viser server on 127.0.0.1 at a free port that answers only requests carrying `secret`
    in PROXY_HEADER. RuntimeError if this viser version cannot be guarded (then nothing runs)."""
    used = threading.Event()
    # viser prints its internal URL whatever `verbose` says: a dead end for an operator.
    with _guarded_serve(secret, used), contextlib.redirect_stdout(io.StringIO()):
        server = _Viser(host="127.0.0.1", port=0, label=label, verbose=False)
    if not used.is_set() or not hasattr(server._websock_server, "_live_connections"):
        server.stop()
        raise RuntimeError(
            f"viser {viser.__version__} does not start its server the way covey guards it; "
            "install the locked versions (requirements.lock)"
        )
    return server


def operator_of(server: viser.ViserServer, client_id: int) -> str | None:
    """The operator whose session opened tab `client_id` (from the gate's header), or None."""
    connection = server._websock_server._live_connections.get(client_id)
    request = getattr(connection, "request", None)
    return request.headers.get(OPERATOR_HEADER) if request is not None else None
