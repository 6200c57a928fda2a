"""A MAVLink 2 link over UDP that never lets bad input through as an exception.

`udpout:HOST:PORT` sends to a fixed peer (a MAVSDK `udpin://` listener, say) and reads its
replies on the same socket; `udpin:HOST:PORT` binds and answers whoever sent the last valid
MAVLink packet. A UDP datagram carries whole MAVLink packets, so every datagram is parsed on its
own: garbage in one cannot swallow the packets of the next.

Both ends of covey's MAVLink use it: the agent's relay backend (agent/backends/relay.py) and the
PX4 emulator (firmware/sitl), so the link the relay flies with is the one the emulator tests.
"""

from __future__ import annotations

import logging
import socket
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

MAX_DATAGRAM_BYTES = 65535
RECEIVE_BUFFER_BYTES = 1 << 20


@dataclass(frozen=True)
class LinkUrl:
    """A parsed link address."""

    listen: bool
    """True for `udpin` (bind and answer), False for `udpout` (send to a fixed peer)."""
    host: str
    port: int

    @classmethod
    def parse(cls, url: str) -> LinkUrl:
        """`udpin:HOST:PORT` / `udpout:HOST:PORT` (also with `://`)."""
        scheme, sep, rest = url.partition(":")
        rest = rest.removeprefix("//")
        host, _, port_text = rest.rpartition(":")
        if not sep or scheme not in ("udpin", "udpout") or not host or not port_text.isdigit():
            raise ValueError(
                f"link must look like udpin:HOST:PORT or udpout:HOST:PORT, got {url!r}"
            )
        port = int(port_text)
        if not 0 <= port <= 65535 or (port == 0 and scheme == "udpout"):
            raise ValueError(f"bad UDP port in {url!r}")
        return cls(scheme == "udpin", host, port)


class UdpLink:
    """One MAVLink link. Use as a context manager."""

    def __init__(self, url: str, src_system: int, src_component: int) -> None:
        self.url = LinkUrl.parse(url)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        # Callers drain the socket once per loop tick; a roomy buffer rides out bursts between ticks.
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        self.peer: tuple[str, int] | None = None
        if self.url.listen:
            self.sock.bind((self.url.host, self.url.port))
        else:
            self.peer = (self.url.host, self.url.port)
        # pymavlink writes packed messages to `file`; we are that file.
        self.mav = mavlink.MAVLink(self, srcSystem=src_system, srcComponent=src_component)
        self.bad_packets = 0
        """Datagrams or packets that did not parse (garbage, bad CRC)."""

    @property
    def local_port(self) -> int:
        return int(self.sock.getsockname()[1])

    def fileno(self) -> int:
        return self.sock.fileno()

    def write(self, buf: bytes) -> None:
        """pymavlink's output hook: one packet, one datagram."""
        if self.peer is None:
            return  # nobody has spoken to this udpin link yet
        try:
            self.sock.sendto(buf, self.peer)
        except OSError as exc:  # peer gone (ICMP unreachable) or buffer full: drop, like UDP
            log.debug("send to %s failed: %s", self.peer, exc)

    def send(self, msg: Any) -> None:
        self.mav.send(msg)

    def receive(self) -> list[Any]:
        """Every valid message waiting on the socket (non-blocking)."""
        out: list[Any] = []
        while True:
            try:
                data, addr = self.sock.recvfrom(MAX_DATAGRAM_BYTES)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError as exc:  # ICMP port unreachable from an earlier send, etc.
                log.debug("receive failed: %s", exc)
                return out
            msgs = self._parse(data)
            if msgs and self.url.listen:
                self.peer = addr
            out.extend(msgs)

    def _parse(self, data: bytes) -> list[Any]:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:  # noqa: BLE001 - pymavlink raises many kinds on garbage
            self.bad_packets += 1
            log.debug("unparsable datagram (%d bytes): %s", len(data), exc)
            return []
        good = [m for m in msgs if m.get_type() != "BAD_DATA"]
        self.bad_packets += len(msgs) - len(good) + (1 if not msgs and data else 0)
        return good

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> UdpLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
