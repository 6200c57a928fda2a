"""What one browser tab's form shows at the moment a button was pressed.

Why this exists: viser's browser client sends every GUI change through ONE shared throttled
sender (50 ms, latest-wins across *all* inputs; viser >= 1.0.27, `makeThrottledMessageSender`).
When two fields and a button change within one throttle window, only the first and the last
message leave the browser: an edit in between is dropped for good, and the server's copy of that
field keeps its old value while the page shows the new one. A command built from the server's
copies could therefore fly an altitude or address vehicles that the operator never saw.

So the station never builds a command from its own copies. A small script, installed once per
tab, records the labelled inputs of the panel in the capture phase of every button click, before
viser's own handler runs, and keeps that snapshot in the tab's localStorage. The button's
callback reads the snapshot of *that* tab over viser's request/response localStorage channel
(`ClientHandle.local_storage.get_item`) and builds the command from it. A snapshot that is
missing, late, malformed or taken for another button is refused with a message; nothing is sent.

The same script gives every labelled input its label as its accessible name (viser links labels
with `for=`, which its text fields do not answer), so screen readers and `getByLabel` find them.
"""

from __future__ import annotations

import json
import secrets
import threading
from collections.abc import Iterable
from dataclasses import dataclass

import viser
from viser import _messages as viser_messages

from groundstation.inputs import InputError

STORAGE_KEY = "covey.form"
"""localStorage key stem (viser namespaces it); each install appends its token."""
_VISER_STORAGE_PREFIX = "viser-user:"
"""The namespace viser's client puts in front of keys read through `local_storage.get_item`."""

_SCRIPT = """
(() => {
  const labels = new Set(%(labels)s);
  // One key per install: tabs of one origin share localStorage, and must not read each other's.
  const previous = window.__coveyForm;
  if (previous !== undefined) localStorage.removeItem(previous.key);
  window.__coveyForm = {key: %(key)s, token: %(token)s, seq: 0};
  // A reconnect installs again with a new token; the listeners are added once per page.
  if (previous !== undefined) return;
  // The input a viser label names: the one in the label's row.
  const inputOf = (label) => {
    const row = label.closest(".mantine-Flex-root");
    return row && row.querySelector("input, textarea");
  };
  const fields = () => {
    const values = {};
    for (const label of document.querySelectorAll("label")) {
      const name = label.textContent.trim();
      if (!labels.has(name)) continue;
      const input = inputOf(label);
      if (!input) continue;
      values[name] = input.type === "checkbox" ? String(input.checked) : input.value;
    }
    return values;
  };
  // Accessible names: viser's label points (for=) at an id that some inputs (text fields) do
  // not carry, so screen readers and getByLabel found no name. Name each such input by its
  // label, again whenever the panel re-renders.
  const name = () => {
    for (const label of document.querySelectorAll("label[for]")) {
      if (label.control) continue;
      const input = inputOf(label);
      const text = label.textContent.trim();
      if (input && text && input.getAttribute("aria-label") !== text) {
        input.setAttribute("aria-label", text);
      }
    }
  };
  let queued = false;
  new MutationObserver(() => {
    if (queued) return;
    queued = true;
    requestAnimationFrame(() => { queued = false; name(); });
  }).observe(document.body, {childList: true, subtree: true});
  name();
  document.addEventListener("click", (event) => {
    const button = event.target instanceof Element ? event.target.closest("button") : null;
    if (!button) return;
    const form = window.__coveyForm;
    form.seq += 1;
    localStorage.setItem(form.key, JSON.stringify({token: form.token, seq: form.seq,
      button: button.textContent.trim(), values: fields()}));
  }, true);
})();
"""


@dataclass(frozen=True)
class FormSnapshot:
    """The labelled inputs of one tab, as shown when `button` was clicked."""

    button: str
    """The visible text of the button that was clicked."""
    values: dict[str, str]
    """Input label -> the text its input showed ("true"/"false" for a checkbox)."""
    seq: int
    """The tab's click counter since the script was installed (1 for the first click)."""
    token: str
    """The install token of the tab that took it (a stale record from another page has another)."""

    def get(self, label: str) -> str:
        """The value shown in the input labelled `label`; InputError if the tab had none."""
        if label not in self.values:
            raise InputError(
                f"{label}: the form did not show this field when the button was pressed"
            )
        return self.values[label]


def storage_key(token: str) -> str:
    """The localStorage key under which the tab installed with `token` keeps its last snapshot."""
    return f"{STORAGE_KEY}.{token}"


class BrowserForms:
    """Installs the click-snapshot script in every tab and reads a tab's snapshot back."""

    def __init__(
        self, server: viser.ViserServer, labels: Iterable[str], timeout_s: float = 5.0
    ) -> None:
        if not hasattr(viser.LocalStorageHandle, "get_item") or not hasattr(
            viser_messages, "RunJavascriptMessage"
        ):  # pragma: no cover - guarded by the locked viser version
            raise RuntimeError(
                f"viser {viser.__version__} lacks the localStorage channel covey's panel needs; "
                "install the locked versions (requirements.lock)"
            )
        self.timeout_s = timeout_s
        self._labels = json.dumps(sorted(set(labels)))
        self._lock = threading.Lock()
        self._tabs: dict[int, tuple[str, int]] = {}  # client id -> (token, last seq used)
        server.on_client_connect(self._install)
        server.on_client_disconnect(self._forget)

    def _install(self, client: viser.ClientHandle) -> None:
        token = secrets.token_hex(8)
        with self._lock:
            self._tabs[client.client_id] = (token, 0)
        script = _SCRIPT % {
            "labels": self._labels,
            "key": json.dumps(_VISER_STORAGE_PREFIX + storage_key(token)),
            "token": json.dumps(token),
        }
        # Sent to this tab only: a server-wide message would be replayed into the scene record.
        client._websock_connection.queue_message(viser_messages.RunJavascriptMessage(source=script))

    def _forget(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._tabs.pop(client.client_id, None)

    def read(self, client: viser.ClientHandle | None, button: str) -> FormSnapshot:
        """The snapshot `client`'s tab took when `button` was pressed; InputError if it cannot
        be had, so that the caller sends nothing."""
        if client is None:
            raise InputError(f"{button}: no browser tab is attached to this click; nothing sent")
        try:
            with self._lock:
                token = self._tabs.get(client.client_id, ("", 0))[0]
            raw = client.local_storage.get_item(storage_key(token), timeout=self.timeout_s)
        except (TimeoutError, RuntimeError) as exc:
            raise InputError(
                f"{button}: the browser did not report its form ({exc}); nothing sent"
            ) from None
        snap = parse_snapshot(raw)
        if snap.button != button:
            raise InputError(
                f"{button}: another button ({snap.button!r}) was pressed at the same moment; "
                "nothing sent, press again"
            )
        with self._lock:
            token, last_seq = self._tabs.get(client.client_id, ("", 0))
            fresh = snap.token == token and snap.seq > last_seq
            if fresh:
                self._tabs[client.client_id] = (token, snap.seq)
        if not fresh:
            raise InputError(
                f"{button}: the browser's record of the form is not from this click; "
                "nothing sent, press again"
            )
        return snap


def parse_snapshot(raw: str | None) -> FormSnapshot:
    """A snapshot from its stored JSON; InputError (with the reason) for anything else."""
    if raw is None:
        raise InputError(
            "the browser has no record of the form at the click; nothing sent, press again"
        )
    try:
        data = json.loads(raw)
        button, values, seq, token = data["button"], data["values"], data["seq"], data["token"]
    except (ValueError, TypeError, KeyError) as exc:
        raise InputError(f"the browser's form record is malformed ({exc}); nothing sent") from None
    ok = (
        isinstance(button, str)
        and isinstance(token, str)
        and isinstance(seq, int)
        and isinstance(values, dict)
        and all(isinstance(k, str) and isinstance(v, str) for k, v in values.items())
    )
    if not ok:
        raise InputError("the browser's form record has the wrong types; nothing sent")
    return FormSnapshot(button=button, values=dict(values), seq=seq, token=token)
