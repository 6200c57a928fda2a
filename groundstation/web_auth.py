"""Who may use the browser ground station: the login token, operator accounts, session cookies,
and the Origin and Host checks, as one pure gate in front of the web app.

As Jupyter does it: the station prints a URL with a random token (`/?token=...`); visiting it
sets a session cookie (HttpOnly, SameSite=Strict, Secure over TLS) and redirects to the clean
URL. With a password file, operators log in by name and password instead, and the account name
names the operator of every command. A request is let through to the web app only with a valid
session cookie, from the page's own origin (or one of `allow_origins`), to a Host that is this
station's; everything else is answered here (401 with a login form, or 403) and never reaches
viser. The gate is pure: no sockets, the clock is passed in; groundstation.web_proxy does the I/O.

Password hashes are stdlib scrypt: `scrypt$<n>$<r>$<p>$<salt b64>$<hash b64>`, one account per
line of the password file: `name:<hash>`.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import html
import ipaddress
import os
import re
import secrets
import stat
import urllib.parse
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")
"""An operator name (account or token label): it goes into HTTP headers and the command log."""
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
"""scrypt cost: ~16 MiB and ~50 ms per check, so a guessed password costs a guesser as much."""
MAX_PASSWORD_FILE_BYTES = 1 << 20
"""A password file larger than this is refused (it is a list of operators)."""
LOGIN_PATH = "/login"
"""Where the password form posts."""
PROXY_HEADER = "X-Covey-Proxy"
"""Header that proves to the web app's internal port that the request came through the gate."""
OPERATOR_HEADER = "X-Covey-Operator"
"""Header that tells the web app which operator's session opened a websocket."""
FAILED_LOGINS_PER_MINUTE = 30
"""Failed logins answered per minute; more get 429 until the minute has passed."""


@dataclass(frozen=True)
class GateConfig:
    """Who may use the web app, as the station configured it."""

    scheme: str
    """"https" with TLS, else "http"."""
    port: int
    """The public port (the cookie's name carries it: cookies do not separate ports)."""
    bind_host: str
    """The address the station listens on (a loopback bind only answers loopback Host names)."""
    token: str | None = None
    """The login token; None with a password file (token login is then off)."""
    token_label: str = "operator"
    """The operator name of a token login."""
    accounts: Mapping[str, str] = field(default_factory=dict)
    """Account name -> scrypt hash (the password file); empty: token login only."""
    allow_origins: tuple[str, ...] = ()
    """Further origins (scheme://host[:port]) allowed to open the websocket (reverse proxies)."""
    session_max_age_s: float = 12 * 3600.0
    """How long a login lasts."""

    @property
    def cookie_name(self) -> str:
        return f"covey_session_{self.port}"


@dataclass(frozen=True)
class Decision:
    """What to do with one request: pass it to the web app for `operator`, or answer it here."""

    operator: str | None = None
    """Set: let it through, as this operator's."""
    status: int = 0
    reason: str = ""
    headers: tuple[tuple[str, str], ...] = ()
    body: bytes = b""

    @property
    def allowed(self) -> bool:
        return self.operator is not None


# -- passwords -----------------------------------------------------------------------------------
def hash_password(password: str, *, salt: bytes | None = None) -> str:
    """A scrypt hash of `password` for a password file line."""
    salt = salt if salt is not None else secrets.token_bytes(16)
    digest = hashlib.scrypt(
        password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32
    )
    b64 = base64.b64encode
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b64(salt).decode()}${b64(digest).decode()}"


def _parse_hash(stored: str) -> tuple[int, int, int, bytes, bytes]:
    parts = stored.split("$")
    if len(parts) != 6 or parts[0] != "scrypt":
        raise ValueError(
            "not a scrypt$n$r$p$salt$hash line (write one with covey gcs --hash-password)"
        )
    n, r, p = (int(x) for x in parts[1:4])
    if not (2 <= n <= 2**20 and n & (n - 1) == 0 and 1 <= r <= 32 and 1 <= p <= 16):
        raise ValueError(f"scrypt cost n={n} r={r} p={p} is out of range")
    salt, digest = (
        base64.b64decode(parts[4], validate=True),
        base64.b64decode(parts[5], validate=True),
    )
    if not 8 <= len(salt) <= 64 or not 16 <= len(digest) <= 64:
        raise ValueError("salt or hash has the wrong length")
    return n, r, p, salt, digest


def verify_password(stored: str, password: str) -> bool:
    """True if `password` matches the scrypt hash `stored` (constant-time compare)."""
    try:
        n, r, p, salt, digest = _parse_hash(stored)
    except ValueError:
        return False
    got = hashlib.scrypt(
        password.encode(), salt=salt, n=n, r=r, p=p, dklen=len(digest), maxmem=256 << 20
    )
    return hmac.compare_digest(got, digest)


def read_password_file(path: str | os.PathLike) -> dict[str, str]:
    """Accounts from a password file (`name:<scrypt hash>` lines; # comments). ValueError, with
    the line, for a file that is missing, readable by group or others, or malformed."""
    p = Path(path)
    try:
        info = p.stat()
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"--password-file {p}: not a regular file")
        if info.st_mode & 0o077:
            raise ValueError(
                f"--password-file {p} is readable by group or others (mode "
                f"{stat.S_IMODE(info.st_mode):o}): chmod 600 {p}"
            )
        if info.st_size > MAX_PASSWORD_FILE_BYTES:
            raise ValueError(f"--password-file {p} is larger than {MAX_PASSWORD_FILE_BYTES} bytes")
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"--password-file {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ValueError(f"--password-file {p} is not UTF-8 text") from None
    accounts: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, stored = line.partition(":")
        where = f"--password-file {p} line {number}"
        if not sep or not NAME_RE.fullmatch(name):
            raise ValueError(f"{where}: expected name:<hash> with a name of letters, digits, ._@-")
        if name in accounts:
            raise ValueError(f"{where}: account {name!r} appears twice")
        try:
            _parse_hash(stored)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        accounts[name] = stored
    if not accounts:
        raise ValueError(f"--password-file {p} holds no account")
    return accounts


# -- hosts and origins ---------------------------------------------------------------------------
def is_loopback(host: str) -> bool:
    """True for localhost names and loopback addresses (127/8, ::1)."""
    host = host.strip("[]").lower()
    if host in ("localhost", "localhost.", "ip6-localhost") or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def url_host(host: str) -> str:
    """`host` as it goes into a URL (IPv6 addresses in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def parse_origin(text: str) -> str:
    """A normalised origin "scheme://host[:port]" (default ports dropped); ValueError if `text`
    is not an http(s) origin."""
    u = urllib.parse.urlsplit(text.strip())
    if u.scheme not in ("http", "https") or not u.hostname or u.path not in ("", "/"):
        raise ValueError(f"{text!r} is not an origin like https://gcs.example.org[:port]")
    if u.query or u.fragment or u.username or u.password:
        raise ValueError(f"{text!r} is not an origin like https://gcs.example.org[:port]")
    try:
        port = u.port
    except ValueError:
        raise ValueError(f"{text!r} has a bad port") from None
    default = 443 if u.scheme == "https" else 80
    tail = f":{port}" if port is not None and port != default else ""
    return f"{u.scheme}://{url_host(u.hostname)}{tail}"


def _host_name(host_header: str) -> str:
    """The name part of a Host header ("127.0.0.1:8080" -> "127.0.0.1", "[::1]:80" -> "::1")."""
    h = host_header.strip()
    if h.startswith("["):
        return h[1 : h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


# -- sessions ------------------------------------------------------------------------------------
class Sessions:
    """Stateless signed session cookies: `<operator>.<expiry s>.<HMAC>` under a secret made at
    start (a restart logs everyone out; nothing to store, nothing to bound)."""

    def __init__(self, secret: bytes, max_age_s: float) -> None:
        self._secret = secret
        self.max_age_s = max_age_s

    def _mac(self, body: str) -> str:
        mac = hmac.new(self._secret, body.encode(), hashlib.sha256).digest()
        return base64.urlsafe_b64encode(mac).decode().rstrip("=")

    def issue(self, operator: str, now_s: float) -> str:
        body = f"{operator}.{int(now_s + self.max_age_s)}"
        return f"{body}.{self._mac(body)}"

    def check(self, value: str, now_s: float) -> str | None:
        """The operator of a valid, unexpired cookie value, else None."""
        body, _, mac = value.rpartition(".")
        operator, _, expiry = body.rpartition(".")
        if not hmac.compare_digest(mac.encode(), self._mac(body).encode()):
            return None
        if not expiry.isdigit() or int(expiry) < now_s or not NAME_RE.fullmatch(operator):
            return None
        return operator


def _cookie(headers: Mapping[str, str], name: str) -> str | None:
    for part in headers.get("cookie", "").split(";"):
        key, sep, value = part.strip().partition("=")
        if sep and key == name:
            return value
    return None


# -- the gate ------------------------------------------------------------------------------------
_PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>covey: log in</title>
<meta name="viewport" content="width=device-width"><style>body{{font-family:sans-serif;
max-width:26em;margin:4em auto;color:#222}}input{{display:block;width:100%;margin:.3em 0 .8em;
padding:.4em}}button{{padding:.4em 1.2em}}.err{{color:#c5221f}}</style></head><body>
<h2>covey ground station</h2>{error}{form}</body></html>"""
_TOKEN_FORM = """<p>Open the URL that <code>covey gcs</code> printed (it carries a login token),
or paste the token:</p><form method="get" action="/"><label>Token
<input name="token" type="password" autocomplete="off" autofocus></label>
<button type="submit">Log in</button></form>"""
_PASSWORD_FORM = """<form method="post" action="{action}"><label>Operator
<input name="name" autocomplete="username" autofocus></label><label>Password
<input name="password" type="password" autocomplete="current-password"></label>
<button type="submit">Log in</button></form>"""


class Gate:
    """Decides every request to the web app (see the module docstring)."""

    def __init__(
        self,
        cfg: GateConfig,
        *,
        secret: bytes | None = None,
        clock_s: Callable[[], float],
    ) -> None:
        if cfg.token is None and not cfg.accounts:
            raise ValueError("the web app needs a login token or a password file")
        if not NAME_RE.fullmatch(cfg.token_label):
            raise ValueError(
                f"--token-label {cfg.token_label!r}: use 1-64 letters, digits and ._@- "
                "(it names the operator in the command log)"
            )
        self.cfg = cfg
        self.sessions = Sessions(secret or secrets.token_bytes(32), cfg.session_max_age_s)
        self._clock_s = clock_s
        self._origins = {parse_origin(o) for o in cfg.allow_origins}
        self._origin_hosts = {urllib.parse.urlsplit(o).hostname for o in self._origins}
        self._failures: deque[float] = deque()

    # -- answers ---------------------------------------------------------------------------------
    def answer(self, status: int, reason: str, body: str = "", headers: tuple = ()) -> Decision:
        data = body.encode()
        kind = "text/html; charset=utf-8" if body.startswith("<!doctype") else "text/plain"
        base = (
            ("Content-Type", kind),
            ("Cache-Control", "no-store"),
            ("X-Frame-Options", "DENY"),
            ("Referrer-Policy", "no-referrer"),
        )
        return Decision(status=status, reason=reason, headers=base + tuple(headers), body=data)

    def login_page(self, status: int = 401, error: str = "") -> Decision:
        form = _PASSWORD_FORM.format(action=LOGIN_PATH) if self.cfg.accounts else _TOKEN_FORM
        err = f'<p class="err">{html.escape(error)}</p>' if error else ""
        reason = {401: "Unauthorized", 429: "Too Many Requests"}.get(status, "Unauthorized")
        return self.answer(status, reason, _PAGE.format(error=err, form=form))

    def _logged_in(self, operator: str, location: str) -> Decision:
        flags = "HttpOnly; SameSite=Strict; Path=/"
        if self.cfg.scheme == "https":
            flags += "; Secure"
        value = self.sessions.issue(operator, self._clock_s())
        max_age = int(self.cfg.session_max_age_s)
        cookie = f"{self.cfg.cookie_name}={value}; Max-Age={max_age}; {flags}"
        return self.answer(303, "See Other", "", (("Location", location), ("Set-Cookie", cookie)))

    # -- checks ----------------------------------------------------------------------------------
    def _host_ok(self, host_header: str) -> bool:
        """A loopback station answers only loopback Host names (or an allowed origin's host):
        a DNS-rebinding page (evil.example -> 127.0.0.1) is refused before any login form."""
        if not is_loopback(self.cfg.bind_host):
            return True
        name = _host_name(host_header)
        return is_loopback(name) or name in self._origin_hosts

    def origin_ok(self, origin: str | None, host_header: str) -> bool:
        """No Origin (not a browser's cross-origin request), the page's own origin, or an
        allowed one."""
        if origin is None:
            return True
        try:
            got = parse_origin(origin)
        except ValueError:
            return False
        try:
            own = parse_origin(f"{self.cfg.scheme}://{host_header}")
        except ValueError:
            return False
        return got == own or got in self._origins

    def failed_login_budget(self) -> bool:
        """False while more than FAILED_LOGINS_PER_MINUTE logins failed in the last minute."""
        now = self._clock_s()
        while self._failures and now - self._failures[0] > 60.0:
            self._failures.popleft()
        return len(self._failures) < FAILED_LOGINS_PER_MINUTE

    def _failed(self) -> None:
        self._failures.append(self._clock_s())

    def decide(
        self,
        method: str,
        target: str,
        headers: Mapping[str, str],
        *,
        check_password: Callable[[str, str], bool] | None = None,
        body: bytes = b"",
    ) -> Decision:
        """The decision for one request; `headers` with lower-case names. `check_password(name,
        password)` is the (slow) password check, run by the caller off its event loop."""
        host = headers.get("host", "")
        if not host or not self._host_ok(host):
            return self.answer(403, "Forbidden", "covey: Host not allowed\n")
        if not self.origin_ok(headers.get("origin"), host):
            return self.answer(403, "Forbidden", "covey: cross-origin request refused\n")
        url = urllib.parse.urlsplit(target)
        upgrade = headers.get("upgrade", "").lower() == "websocket"
        if method == "POST" and url.path == LOGIN_PATH and self.cfg.accounts and not upgrade:
            return self._password_login(body, check_password)
        query = urllib.parse.parse_qsl(url.query, keep_blank_values=True)
        token = next((v for k, v in query if k == "token"), None)
        if token is not None and not upgrade and method == "GET":
            return self._token_login(token, url, query)
        cookie = _cookie(headers, self.cfg.cookie_name)
        operator = self.sessions.check(cookie, self._clock_s()) if cookie else None
        if operator is not None and method in ("GET", "HEAD"):
            return Decision(operator=operator)
        if upgrade or method not in ("GET", "HEAD"):
            return self.answer(401, "Unauthorized", "covey: log in first\n")
        return self.login_page()

    def _token_login(self, token: str, url, query: list[tuple[str, str]]) -> Decision:
        expected = self.cfg.token
        if expected is None or not hmac.compare_digest(token.encode(), expected.encode()):
            if not self.failed_login_budget():
                return self.login_page(429, "Too many failed logins; wait a minute.")
            self._failed()
            return self.login_page(error="That token is not this station's.")
        rest = urllib.parse.urlencode([(k, v) for k, v in query if k != "token"])
        return self._logged_in(
            self.cfg.token_label, (url.path or "/") + (f"?{rest}" if rest else "")
        )

    def _password_login(
        self, body: bytes, check_password: Callable[[str, str], bool] | None
    ) -> Decision:
        if not self.failed_login_budget():
            return self.login_page(429, "Too many failed logins; wait a minute.")
        try:
            form = dict(urllib.parse.parse_qsl(body.decode("utf-8"), max_num_fields=4))
        except (UnicodeDecodeError, ValueError):
            form = {}
        name, password = form.get("name", ""), form.get("password", "")
        check = check_password or self.check_password
        if NAME_RE.fullmatch(name) and name in self.cfg.accounts and check(name, password):
            return self._logged_in(name, "/")
        self._failed()
        return self.login_page(error="Wrong operator name or password.")

    def check_password(self, name: str, password: str) -> bool:
        stored = self.cfg.accounts.get(name)
        return stored is not None and verify_password(stored, password)
