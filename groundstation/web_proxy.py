"""The station's public web port: a small authenticating reverse proxy in front of viser.

    sock = bind_listener("127.0.0.1", 8080)            # next free port if busy
    with WebProxy(sock, gate, upstream_port, secret):  # its own thread and event loop
        ...

Each connection's request head (bounded in size and time) goes to the gate
(groundstation.web_auth). A refused request is answered here and closed: the web app never
sees it. A request that passes is sent to viser's internal port with the gate's secret and the
operator's name added (and the browser's cookies and any header of the gate's own names
removed); then bytes are copied both ways (for a websocket, until either side closes). Plain
HTTP requests get one response per connection, so a second request cannot ride on a connection
whose first one was checked. TLS (HTTPS/WSS) is terminated here when the station has a
certificate.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
from dataclasses import dataclass

from groundstation.web_auth import OPERATOR_HEADER, PROXY_HEADER, Decision, Gate

log = logging.getLogger(__name__)

_DROPPED = {"cookie", PROXY_HEADER.lower(), OPERATOR_HEADER.lower(), "connection", "keep-alive"}
"""Request headers never passed on (the session stays with the gate; the gate's own headers
can only come from the gate)."""


@dataclass(frozen=True)
class ProxyLimits:
    """Bounds on what one client can make the proxy hold."""

    max_head_bytes: int = 16 * 1024
    """Largest request head (request line and headers)."""
    max_body_bytes: int = 4096
    """Largest request body (only the login form has one)."""
    head_timeout_s: float = 10.0
    """A client must send its whole request head within this."""
    max_connections: int = 256
    """Open connections at once; more are closed at once."""


def bind_listener(host: str, port: int, tries: int = 100) -> socket.socket:
    """A listening TCP socket on `host` at `port`, or the next free port above it (any free
    port for 0). OSError if none of `tries` ports is free."""
    family = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0][0]
    last: OSError | None = None
    for candidate in [port] if port == 0 else range(port, min(port + tries, 65536)):
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, candidate))
            sock.listen(128)
        except OSError as exc:
            sock.close()
            last = exc
            continue
        sock.setblocking(False)
        return sock
    raise OSError(f"no free web port from {port} ({last})")


def tls_context(certfile: str, keyfile: str) -> ssl.SSLContext:
    """A server TLS context (TLS 1.2+); ValueError naming the file that cannot be used."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(certfile, keyfile)
    except FileNotFoundError as exc:
        raise ValueError(f"--certfile/--keyfile: {exc.filename}: no such file") from None
    except (ssl.SSLError, OSError) as exc:
        raise ValueError(
            f"--certfile {certfile} / --keyfile {keyfile}: not a certificate and its key ({exc})"
        ) from None
    return ctx


def _response(d: Decision) -> bytes:
    lines = [f"HTTP/1.1 {d.status} {d.reason}"]
    lines += [f"{k}: {v}" for k, v in d.headers]
    lines += [f"Content-Length: {len(d.body)}", "Connection: close", "", ""]
    return "\r\n".join(lines).encode("latin-1") + d.body


def _parse_head(head: bytes) -> tuple[str, str, list[tuple[str, str]]] | None:
    """(method, target, headers) of a request head, or None if it is not HTTP/1.1."""
    try:
        text = head.decode("latin-1")
    except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes every byte
        return None
    request_line, *rest = text.split("\r\n")
    parts = request_line.split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1.") or not parts[1].startswith("/"):
        return None
    headers = []
    for line in rest:
        if not line:
            continue
        name, sep, value = line.partition(":")
        if not sep or not name or name != name.strip() or any(c in name for c in " \t"):
            return None
        headers.append((name, value.strip()))
    return parts[0], parts[1], headers


class WebProxy:
    """Context manager: the authenticating proxy on `sock`, in front of 127.0.0.1:upstream_port."""

    def __init__(
        self,
        sock: socket.socket,
        gate: Gate,
        upstream_port: int,
        secret: str,
        *,
        ssl_context: ssl.SSLContext | None = None,
        limits: ProxyLimits | None = None,
    ) -> None:
        self._sock = sock
        self.gate = gate
        self._upstream_port = upstream_port
        self._secret = secret
        self._ssl = ssl_context
        self.limits = limits or ProxyLimits()
        self.port: int = sock.getsockname()[1]
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopped: asyncio.Event | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self.refused = 0
        """Requests answered by the gate instead of the web app (401, 403, 429, 400)."""

    # -- lifecycle -------------------------------------------------------------------------------
    def __enter__(self) -> WebProxy:
        ready = threading.Event()
        failed: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(self._serve(ready))
            except BaseException as exc:  # noqa: BLE001 - handed to the starting thread
                failed.append(exc)
                ready.set()
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="gcs-web", daemon=True)
        self._thread.start()
        ready.wait()
        if failed:
            self.close()
            raise failed[0]
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        loop, stopped = self._loop, self._stopped
        if loop is not None and stopped is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stopped.set)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with contextlib.suppress(OSError):
            self._sock.close()

    async def _serve(self, ready: threading.Event) -> None:
        self._stopped = asyncio.Event()
        server = await asyncio.start_server(
            self._handle,
            sock=self._sock,
            ssl=self._ssl,
            limit=self.limits.max_head_bytes,
            ssl_handshake_timeout=self.limits.head_timeout_s if self._ssl else None,
        )
        ready.set()
        async with server:
            await self._stopped.wait()
            server.close()
            for w in list(self._writers):
                w.close()
        await asyncio.sleep(0)

    # -- one connection --------------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._writers) >= self.limits.max_connections:
            writer.close()
            return
        self._writers.add(writer)
        try:
            await self._request(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, ssl.SSLError, TimeoutError):
            pass
        except Exception:  # noqa: BLE001 - one bad client never stops the proxy
            log.exception("web proxy: a connection failed")
        finally:
            self._writers.discard(writer)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    async def _refuse(self, writer: asyncio.StreamWriter, d: Decision) -> None:
        self.refused += 1
        writer.write(_response(d))
        await writer.drain()

    async def _request(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        limits = self.limits
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), limits.head_timeout_s)
        except asyncio.LimitOverrunError:
            await self._refuse(writer, self.gate.answer(431, "Request Header Fields Too Large"))
            return
        parsed = _parse_head(head[:-4])
        if parsed is None:
            await self._refuse(writer, self.gate.answer(400, "Bad Request", "bad request\n"))
            return
        method, target, header_list = parsed
        headers: dict[str, str] = {}
        for name, value in header_list:
            key = name.lower()
            if key in headers and key in ("host", "origin", "cookie", "content-length"):
                await self._refuse(writer, self.gate.answer(400, "Bad Request", "bad request\n"))
                return
            headers[key] = value
        body = b""
        if method == "POST":
            if "transfer-encoding" in headers:
                await self._refuse(writer, self.gate.answer(411, "Length Required"))
                return
            try:
                length = int(headers.get("content-length", "0"))
            except ValueError:
                length = -1
            if not 0 <= length <= limits.max_body_bytes:
                await self._refuse(writer, self.gate.answer(413, "Content Too Large"))
                return
            body = await asyncio.wait_for(reader.readexactly(length), limits.head_timeout_s)
            loop = asyncio.get_running_loop()  # the password check is slow (scrypt): off-loop
            decision = await loop.run_in_executor(
                None, lambda: self.gate.decide(method, target, headers, body=body)
            )
        else:
            decision = self.gate.decide(method, target, headers)
        if not decision.allowed:
            await self._refuse(writer, decision)
            return
        await self._pass_on(reader, writer, method, target, header_list, headers, decision)

    async def _pass_on(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        method: str,
        target: str,
        header_list: list[tuple[str, str]],
        headers: dict[str, str],
        decision: Decision,
    ) -> None:
        upgrade = headers.get("upgrade", "").lower() == "websocket"
        lines = [f"{method} {target} HTTP/1.1"]
        lines += [f"{k}: {v}" for k, v in header_list if k.lower() not in _DROPPED]
        lines += [
            f"{PROXY_HEADER}: {self._secret}",
            f"{OPERATOR_HEADER}: {decision.operator}",
            "Connection: Upgrade" if upgrade else "Connection: close",
            "",
            "",
        ]
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self._upstream_port)
        try:
            up_writer.write("\r\n".join(lines).encode("latin-1"))
            await up_writer.drain()
            down = asyncio.ensure_future(_copy(up_reader, writer))
            if not upgrade:  # one request per connection: nothing more is read from the client
                await down
                return
            up = asyncio.ensure_future(_copy(reader, up_writer))
            _, pending = await asyncio.wait({down, up}, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        finally:
            up_writer.close()
            with contextlib.suppress(Exception):
                await up_writer.wait_closed()


async def _copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    with contextlib.suppress(ConnectionError, ssl.SSLError):
        while data := await src.read(65536):
            dst.write(data)
            await dst.drain()
