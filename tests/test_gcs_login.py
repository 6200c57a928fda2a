"""The browser station's login (issue 34, finding 1): token URL, session cookie, operator
accounts, the Origin and Host checks, the guarded internal port, TLS, and the refusals of
`covey gcs` set-ups that would expose it. Real station, real sockets, real viser; the attack
client is tests/gcs_attack.py (the issue's own attack)."""

from __future__ import annotations

import datetime
import http.client
import ssl
import subprocess
import sys
from pathlib import Path

import pytest
from gcs_attack import attack

from comms.mesh import Mesh
from comms.session import embedded_router, free_tcp_port
from groundstation.station import GcsConfig, GroundStation
from groundstation.web_auth import hash_password, read_password_file, verify_password
from groundstation.web_viser import operator_of

REPO = Path(__file__).resolve().parent.parent
FLEET = "login"


@pytest.fixture(scope="module")
def mesh():
    with Mesh(embedded_router(free_tcp_port(), fleet=FLEET)) as m:
        yield m


@pytest.fixture(scope="module")
def station(mesh):
    with GroundStation(GcsConfig(port=0, token_label="alice"), mesh=mesh) as gs:
        yield gs


def get(port: int, target: str, headers: dict | None = None, *, tls: ssl.SSLContext | None = None):
    """(status, headers, body) of one request to 127.0.0.1:port."""
    if tls is not None:
        c = http.client.HTTPSConnection("127.0.0.1", port, context=tls, timeout=10)
    else:
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        c.request("GET", target, headers=headers or {})
        r = c.getresponse()
        return r.status, r, r.read()
    finally:
        c.close()


def post(port: int, target: str, body: str, headers: dict) -> tuple[int, http.client.HTTPResponse]:
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=20)
    try:
        c.request(
            "POST",
            target,
            body=body,
            headers={"Content-Type": "application/x-www-form-urlencoded", **headers},
        )
        r = c.getresponse()
        r.read()
        return r.status, r
    finally:
        c.close()


def login(gs: GroundStation) -> str:
    """The session cookie ("name=value") the token URL sets."""
    status, r, _ = get(gs.port, gs.url.split(f":{gs.port}", 1)[1])
    assert status == 303 and r.getheader("Location") == "/", status
    return r.getheader("Set-Cookie").split(";", 1)[0]


VISER_PAGE = b'<html lang="en">'  # viser's index.html; the login page is covey's own


def test_url_carries_a_token_that_sets_a_strict_httponly_cookie(station):
    assert "/?token=" in station.url
    status, r, body = get(station.port, station.url.split(f":{station.port}", 1)[1])
    assert status == 303 and body == b""
    cookie = r.getheader("Set-Cookie")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Secure" not in cookie
    assert cookie.startswith(f"covey_session_{station.port}=alice.")
    status, _, body = get(station.port, "/", {"Cookie": cookie.split(";")[0]})
    assert status == 200 and VISER_PAGE in body


@pytest.mark.parametrize(
    "target, headers",
    [
        ("/", {}),
        ("/?token=wrong", {}),
        ("/index.html", {"Cookie": "covey_session_1=alice.9999999999.forged"}),
    ],
    ids=["no-session", "wrong-token", "forged-cookie"],
)
def test_no_session_gets_the_login_form_and_no_page(station, target, headers):
    status, _, body = get(station.port, target, headers)
    assert status == 401
    assert VISER_PAGE not in body and b"covey ground station" in body


def test_a_forged_cookie_of_the_right_name_is_refused(station):
    cookie = login(station)
    name, value = cookie.split("=", 1)
    forged = f"{name}=bob{value[len('alice') :]}"  # another operator, same signature
    assert get(station.port, "/", {"Cookie": forged})[0] == 401


def test_websocket_needs_a_session_and_the_pages_own_origin(station):
    ws = f"ws://127.0.0.1:{station.port}/"
    own = f"http://127.0.0.1:{station.port}"
    cookie = login(station)
    no_session = attack(ws, [], origin=own, timeout_s=3)
    foreign = attack(ws, [], cookie=cookie, timeout_s=3)  # Origin: http://evil.example
    other_port = attack(ws, [], cookie=cookie, origin="http://127.0.0.1:1", timeout_s=3)
    assert (no_session.refused, no_session.status, no_session.frames) == (True, 401, 0)
    assert (foreign.refused, foreign.status, foreign.frames) == (True, 403, 0)
    assert (other_port.refused, other_port.status, other_port.frames) == (True, 403, 0)
    # The same client, logged in and from the page's origin, gets the station (and its token).
    ok = attack(ws, [], cookie=cookie, origin=own, timeout_s=5)
    assert not ok.refused and ok.frames > 0 and ok.token


def test_the_internal_viser_port_answers_nothing_without_the_gates_secret(station):
    inner = station.server.get_port()
    assert inner != station.port
    status, _, body = get(inner, "/")
    assert status == 403 and VISER_PAGE not in body
    cookie = login(station)
    direct = attack(
        f"ws://127.0.0.1:{inner}/", [], cookie=cookie, origin=f"http://127.0.0.1:{inner}"
    )
    assert (direct.refused, direct.status, direct.frames) == (True, 403, 0)


def test_a_foreign_host_header_is_refused(station):
    cookie = login(station)
    status, _, body = get(
        station.port, "/", {"Host": f"evil.example:{station.port}", "Cookie": cookie}
    )
    assert status == 403 and VISER_PAGE not in body


def test_the_logged_in_tab_carries_its_operator(station):
    cookie = login(station)
    own = f"http://127.0.0.1:{station.port}"
    seen: list[str | None] = []
    station.server.on_client_connect(
        lambda c: seen.append(operator_of(station.server, c.client_id))
    )
    result = attack(f"ws://127.0.0.1:{station.port}/", [], cookie=cookie, origin=own, timeout_s=5)
    assert result.token and seen == ["alice"]


# -- operator accounts -------------------------------------------------------------------------
def test_password_hash_round_trip():
    stored = hash_password("correct horse", salt=b"0123456789abcdef")
    assert verify_password(stored, "correct horse")
    assert not verify_password(stored, "correct hors")
    assert not verify_password("scrypt$1$1$1$AA==$AA==", "x")


def test_password_file_refusals(tmp_path):
    f = tmp_path / "operators"
    f.write_text(f"bob:{hash_password('hunter2hunter2')}\n")
    f.chmod(0o640)
    with pytest.raises(ValueError, match="readable by group or others"):
        read_password_file(f)
    f.chmod(0o600)
    assert set(read_password_file(f)) == {"bob"}
    f.write_text("bob:plaintext\n")
    with pytest.raises(ValueError, match="line 1"):
        read_password_file(f)


def test_password_login(mesh, tmp_path):
    f = tmp_path / "operators"
    f.write_text(f"# operators\nbob:{hash_password('hunter2hunter2')}\n")
    f.chmod(0o600)
    cfg = GcsConfig(port=0, gcs_id=3, password_file=str(f))
    with GroundStation(cfg, mesh=mesh) as gs:
        assert "token" not in gs.url
        own = {"Origin": f"http://127.0.0.1:{gs.port}"}
        assert post(gs.port, "/login", "name=bob&password=wrong", own)[0] == 401
        assert post(gs.port, "/login", "name=eve&password=hunter2hunter2", own)[0] == 401
        assert get(gs.port, f"/?token={'x' * 32}")[0] == 401  # token login is off
        # A foreign page cannot log the operator in (login CSRF): the Origin check comes first.
        foreign = {"Origin": "http://evil.example"}
        assert post(gs.port, "/login", "name=bob&password=hunter2hunter2", foreign)[0] == 403
        status, r = post(gs.port, "/login", "name=bob&password=hunter2hunter2", own)
        assert status == 303
        cookie = r.getheader("Set-Cookie").split(";")[0]
        assert cookie.startswith(f"covey_session_{gs.port}=bob.")
        assert get(gs.port, "/", {"Cookie": cookie})[0] == 200


# -- TLS ---------------------------------------------------------------------------------------
def self_signed(tmp_path: Path) -> tuple[str, str]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    import ipaddress

    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .sign(key, hashes.SHA256())
    )
    certfile, keyfile = tmp_path / "gcs.crt", tmp_path / "gcs.key"
    certfile.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    keyfile.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return str(certfile), str(keyfile)


def test_https_and_wss_with_a_certificate(mesh, tmp_path):
    certfile, keyfile = self_signed(tmp_path)
    cfg = GcsConfig(port=0, gcs_id=4, certfile=certfile, keyfile=keyfile)
    with GroundStation(cfg, mesh=mesh) as gs:
        assert gs.url.startswith("https://127.0.0.1:")
        trust = ssl.create_default_context(cafile=certfile)
        status, r, _ = get(gs.port, gs.url.split(f":{gs.port}", 1)[1], tls=trust)
        cookie = r.getheader("Set-Cookie")
        assert status == 303 and "Secure" in cookie
        cookie = cookie.split(";")[0]
        status, _, body = get(gs.port, "/", {"Cookie": cookie}, tls=trust)
        assert status == 200 and VISER_PAGE in body
        with pytest.raises(ConnectionError):  # plain HTTP to the TLS port gets nothing
            get(gs.port, "/", {"Cookie": cookie})
        own = f"https://127.0.0.1:{gs.port}"
        # up to three tries: once, on a loaded 2-core CI machine, the upgrade's connection was
        # closed before any response (InvalidMessage); a refusal would answer with a status
        for _ in range(3):
            wss = attack(f"wss://127.0.0.1:{gs.port}/", [], cookie=cookie, origin=own, tls=trust)
            if wss.status or not wss.error.startswith("InvalidMessage"):
                break
        assert not wss.refused and wss.token, wss


# -- `covey gcs` refusals: one line, exit 2 -----------------------------------------------------
def gcs_cli(*args: str, stdin: str = "") -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "covey_cli", "gcs", *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )


@pytest.mark.parametrize(
    "args, says",
    [
        (["--host", "0.0.0.0"], "--insecure-http"),
        (["--certfile", "x.pem"], "go together"),
        (["--host", "0.0.0.0", "--insecure-http", "--certfile", "x", "--keyfile", "y"], "choose"),
        (["--allow-origin", "evil.example"], "not an origin"),
        (["--token-label", "a b"], "--token-label"),
    ],
    ids=["open-host", "half-tls", "tls-and-insecure", "bad-origin", "bad-label"],
)
def test_cli_refuses_exposed_or_bad_web_setups(args, says):
    r = gcs_cli("--connect", "tcp/127.0.0.1:9", *args)
    assert r.returncode == 2, r.stderr
    # Set-up errors are one line; argparse's own (a bad value) add its usage above the line.
    *usage, last = r.stderr.strip().splitlines()
    assert says in last and "Traceback" not in r.stderr, r.stderr
    assert not usage or usage[0].startswith("usage:"), r.stderr
    if args[0] != "--allow-origin":  # checked by covey, not by argparse: one line
        assert not usage, r.stderr


def test_cli_refuses_a_readable_password_file_and_hashes_one(tmp_path):
    r = gcs_cli("--hash-password", "carol", stdin="s3cret-pass\n")
    assert r.returncode == 0, r.stderr
    name, stored = r.stdout.strip().split(":", 1)
    assert name == "carol" and verify_password(stored, "s3cret-pass")
    f = tmp_path / "operators"
    f.write_text(r.stdout)
    f.chmod(0o644)
    r = gcs_cli("--connect", "tcp/127.0.0.1:9", "--password-file", str(f))
    assert r.returncode == 2 and "chmod 600" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# -- real Chromium: a page of another origin cannot drive the station; the logged-in page can ---
FOREIGN_PAGE = """<!doctype html><html><body><script>
window.result = new Promise((resolve) => {
  const out = {opened: false, messages: 0, closed: false, fetched: null};
  const ws = new WebSocket("ws://127.0.0.1:%(port)d/", ["viser-v%(viser)s"]);
  ws.onopen = () => { out.opened = true; };
  ws.onmessage = () => { out.messages += 1; };
  ws.onclose = () => { out.closed = true; };
  fetch("http://127.0.0.1:%(port)d/", {credentials: "include"})
    .then((r) => r.text()).then((t) => { out.fetched = t.length; })
    .catch((e) => { out.fetched = "refused: " + e; });
  setTimeout(() => resolve(out), 4000);
});
</script></body></html>"""


@pytest.fixture
def foreign_site(tmp_path):
    """An HTTP server on another port of 127.0.0.1 (another origin, the same site)."""
    import functools
    import http.server
    import threading

    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    handler.log_message = lambda *a: None  # type: ignore[attr-defined]
    with http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler) as srv:
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        yield tmp_path, srv.server_address[1]
        srv.shutdown()


@pytest.mark.browser
@pytest.mark.e2e
def test_chromium_on_another_origin_cannot_drive_the_station_the_logged_in_page_flies(
    foreign_site,
):
    import shutil
    import urllib.parse

    import viser
    from conftest import wait_until

    from comms.schema import Mode
    from comms.session import MeshConfig
    from groundstation.demo_proc import DemoProcess
    from groundstation.panel import TAKEOFF_ALT, TARGETS

    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("Debian chromium is not installed (apt-get install chromium); CI installs it")
    sync_api = pytest.importorskip("playwright.sync_api")
    from test_gcs_browser import CHROMIUM_ARGS, field

    site, site_port = foreign_site
    with DemoProcess(["--vehicles", "1", "--port", "0"]) as demo:
        port = urllib.parse.urlsplit(demo.url).port
        (site / "attack.html").write_text(FOREIGN_PAGE % {"port": port, "viser": viser.__version__})
        states: dict = {}
        with (
            Mesh(MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))) as mesh,
            sync_api.sync_playwright() as p,
        ):
            mesh.subscribe_states(lambda s, _t: states.__setitem__(s.vehicle_id, s))
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
            context = browser.new_context(viewport={"width": 1200, "height": 800})
            page = context.new_page()
            page.set_default_timeout(60_000)
            page.goto(demo.url)  # logs in: the foreign page below runs with the cookie set
            page.get_by_role("button", name="Takeoff").wait_for()
            assert "token" not in page.url
            evil = context.new_page()
            evil.goto(f"http://127.0.0.1:{site_port}/attack.html")
            out = evil.evaluate("() => window.result")
            assert out["opened"] is False and out["messages"] == 0 and out["closed"], out
            assert str(out["fetched"]).startswith("refused"), out  # 403, and CORS hides it anyway
            assert wait_until(lambda: 1 in states, 30)
            field(page, TARGETS).fill("1")
            field(page, TAKEOFF_ALT).fill("4")
            page.get_by_role("button", name="Takeoff").click(force=True)
            assert wait_until(lambda: states[1].mode is not Mode.LANDED, 30), states
            # The shared command log names the operator of the token login.
            page.locator("[data-command]", has_text="this station (operator)").first.wait_for()
            browser.close()
