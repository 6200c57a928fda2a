"""A fleet's TLS identities and ready-to-use Zenoh configs, made in one step (`covey tls init`).

Writes into a directory outside the repository (default ~/.config/covey/tls, mode 0700):

    ca.pem, ca.key               the fleet CA (keep ca.key off the vehicles)
    <name>.pem, <name>.key       one certificate per identity, signed by the CA; the common name
                                 is the identity the routers' access control matches
    <router>.json5               for each router identity (any name that is not gcs-<id> or
                                 vehicle-<id>): comms/zenoh_configs/router_mtls_acl.json5 with
                                 its paths filled in, and one access-control rule per vehicle
                                 given and the stations given as the ground stations
    gcs-<id>.json5, vehicle-<id>.json5
                                 comms/zenoh_configs/client_mtls.json5 with that identity's files

Keys are written with mode 0600. Certificates are EC P-256, valid `days` days, and name
localhost, 127.0.0.1 and ::1 plus the hosts given (DNS names or IP addresses), so a client can
connect to `tls/localhost:7447` on one machine or to the router's name on a real network.
An existing CA in the directory is reused: identities added later join the same fleet.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from comms.schema import MAX_VEHICLE_ID

CONFIGS = Path(__file__).resolve().parent.parent / "comms" / "zenoh_configs"
"""The shipped templates."""
DEFAULT_DIR = Path("~/.config/covey/tls")
PLACEHOLDER_DIR = "/etc/covey/tls/"
"""Where the shipped templates point; replaced by the real directory."""
CA_NAME = "covey-fleet-ca"
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")
_VEHICLE_RE = re.compile(r"^vehicle-([0-9]{1,5})$")
_STATION_RE = re.compile(r"^gcs-([0-9]{1,5})$")
_SOURCE = Path(__file__).resolve().parent.parent
"""The source tree this module runs from (TLS keys are never written inside it)."""


class TlsSetupError(ValueError):
    """The TLS setup cannot be made as asked; the message is one line that says why."""


@dataclass(frozen=True)
class TlsConfig:
    """What `covey tls init` makes."""

    directory: Path = DEFAULT_DIR
    """Where the CA, the certificates, the keys and the configs go (created 0700)."""
    names: tuple[str, ...] = ("router", "gcs-1", "vehicle-1")
    """Identities: routers (any other name), stations `gcs-<id>`, vehicles `vehicle-<id>`."""
    hosts: tuple[str, ...] = ()
    """Extra DNS names or IP addresses every certificate names (beside the loopback ones)."""
    days: int = 30
    """Validity of new certificates (and of a new CA), in days."""
    configs: bool = True
    """Also write each identity's Zenoh JSON5 config (False: certificates only)."""

    def __post_init__(self) -> None:
        if not self.names:
            raise TlsSetupError("give at least one identity (router, gcs-<id>, vehicle-<id>)")
        for name in self.names:
            check_name(name)
        if len(set(self.names)) != len(self.names):
            raise TlsSetupError(f"identities given twice: {' '.join(self.names)}")
        if not 1 <= self.days <= 3650:
            raise TlsSetupError(f"days={self.days} must be within 1..3650")
        for host in self.hosts:
            _san(host)
        if self.configs:
            if not any(role_of(n) == "router" for n in self.names):
                raise TlsSetupError(
                    "give a router identity (e.g. router): the configs need the router's"
                )
            if not any(role_of(n) == "station" for n in self.names):
                raise TlsSetupError(
                    "give at least one station identity (gcs-<id>): only stations may command "
                    "and push the roster through the router"
                )


def check_name(name: str) -> str:
    """`name` if it can be an identity (a certificate common name and a file name)."""
    if not _NAME_RE.match(name) or name in ("ca", CA_NAME):
        raise TlsSetupError(
            f"identity {name!r} must be 1-63 of A-Z a-z 0-9 _ . - (not 'ca'), e.g. router, "
            "gcs-1, vehicle-3"
        )
    for pattern in (_VEHICLE_RE, _STATION_RE):
        m = pattern.match(name)
        if m and not 1 <= int(m.group(1)) <= MAX_VEHICLE_ID:
            raise TlsSetupError(f"identity {name!r}: the id must be within 1..{MAX_VEHICLE_ID}")
    return name


def role_of(name: str) -> str:
    """ "vehicle", "station" or "router" (every other name)."""
    if _VEHICLE_RE.match(name):
        return "vehicle"
    if _STATION_RE.match(name):
        return "station"
    return "router"


def init(cfg: TlsConfig, now: datetime.datetime | None = None) -> list[Path]:
    """Make (or reuse) the CA, issue a certificate per identity, and write the configs; returns
    the configs written (or the certificates, with `cfg.configs` False). Raises TlsSetupError."""
    d = _private_dir(cfg.directory)
    now = now or datetime.datetime.now(datetime.UTC)
    ca_key, ca_cert = _ca(d, cfg.days, now)
    hosts = tuple(dict.fromkeys((*LOOPBACK_HOSTS, *cfg.hosts)))
    certs = [_issue(d, name, hosts, ca_key, ca_cert, cfg.days, now) for name in cfg.names]
    if not cfg.configs:
        return certs
    stations = [n for n in cfg.names if role_of(n) == "station"]
    vehicles = [
        int(m.group(1))
        for n in cfg.names
        if role_of(n) == "vehicle" and (m := _VEHICLE_RE.match(n)) is not None
    ]
    out = []
    for name in cfg.names:
        if role_of(name) == "router":
            text = router_config(d, name, stations, vehicles)
        else:
            text = _paths(_template("client_mtls.json5"), d, name)
        header = f"// Written by `covey tls init` for {name} (trust/tls_setup.py).\n"
        out.append(_write(d / f"{name}.json5", (header + text).encode(), 0o600))
    return out


def router_config(d: Path, name: str, stations: Sequence[str], vehicles: Sequence[int]) -> str:
    """router_mtls_acl.json5 for router `name` in directory `d`: its files, `stations` as the
    ground stations, and one access-control rule, subject and policy per vehicle id (the
    template's vehicle-1 lines are the pattern; its other example vehicles go)."""
    text = _paths(_template("router_mtls_acl.json5"), d, name)
    text, n = re.subn(
        r"cert_common_names: \[[^\]]*gcs-[^\]]*\]",
        "cert_common_names: [" + ", ".join(f'"{s}"' for s in stations) + "]",
        text,
    )
    if n != 1:
        raise TlsSetupError("router_mtls_acl.json5 has no ground-stations subject to fill in")
    lines = []
    for line in text.splitlines(keepends=True):
        m = re.match(r'\s*\{ id: "vehicle-([0-9]+)"', line)
        if m is None:
            lines.append(line)
        elif m.group(1) == "1":
            lines += [
                line.replace('vehicle-1"', f'vehicle-{v}"').replace("/1/", f"/{v}/")
                for v in sorted(vehicles)
            ]
    return "".join(lines)


def _template(name: str) -> str:
    return (CONFIGS / name).read_text(encoding="utf-8")


def _paths(text: str, d: Path, name: str) -> str:
    for leaf in ("client", "router"):
        text = text.replace(f"{PLACEHOLDER_DIR}{leaf}.pem", _json_str(d / f"{name}.pem"))
        text = text.replace(f"{PLACEHOLDER_DIR}{leaf}.key", _json_str(d / f"{name}.key"))
    return text.replace(f"{PLACEHOLDER_DIR}ca.pem", _json_str(d / "ca.pem"))


def _json_str(path: Path) -> str:
    """A path as it may stand between the template's double quotes."""
    return str(path).replace("\\", "\\\\").replace('"', '\\"')


def _private_dir(directory: Path) -> Path:
    d = Path(directory).expanduser()
    if not str(directory).strip():
        raise TlsSetupError("the TLS directory path is empty (an unset variable?)")
    resolved = d.resolve()
    if resolved == _SOURCE or _SOURCE in resolved.parents:
        raise TlsSetupError(
            f"{d} is inside covey's source tree ({_SOURCE}): TLS keys never go there "
            f"(default {DEFAULT_DIR})"
        )
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise TlsSetupError(f"cannot create {d}: {exc.strerror or exc}") from None
    if not d.is_dir():
        raise TlsSetupError(f"{d} is not a directory")
    return d


def _ca(
    d: Path, days: int, now: datetime.datetime
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    cert_path, key_path = d / "ca.pem", d / "ca.key"
    if cert_path.exists() or key_path.exists():
        try:
            cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        except (OSError, ValueError, TypeError) as exc:
            raise TlsSetupError(
                f"{d} holds a fleet CA that cannot be used ({exc}); move it away to make a new one"
            ) from None
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise TlsSetupError(f"{key_path} is not an EC key")
        return key, cert
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, CA_NAME)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(key_path, _key_pem(key), 0o600)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return key, cert


def _issue(
    d: Path,
    name: str,
    hosts: Iterable[str],
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    days: int,
    now: datetime.datetime,
) -> Path:
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(min(now + datetime.timedelta(days=days), ca_cert.not_valid_after_utc))
        .add_extension(x509.SubjectAlternativeName([_san(h) for h in hosts]), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    _write(d / f"{name}.key", _key_pem(key), 0o600)
    return _write(d / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM), 0o644)


def _san(host: str) -> x509.GeneralName:
    """A subject alternative name: an IP address, or a DNS name (`DNS:` / `IP:` prefixes, as
    openssl writes them, are accepted)."""
    text = host.strip()
    for prefix in ("DNS:", "IP:"):
        if text.upper().startswith(prefix):
            text = text[len(prefix) :]
    try:
        return x509.IPAddress(ipaddress.ip_address(text.strip("[]")))
    except ValueError:
        pass
    if not re.match(
        r"^(?=.{1,253}$)[A-Za-z0-9*]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?)*$",
        text,
    ):
        raise TlsSetupError(f"host {host!r} is neither a DNS name nor an IP address")
    return x509.DNSName(text)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _write(path: Path, data: bytes, mode: int) -> Path:
    """Write atomically with `mode` from the start (a key is never readable by others)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(tmp, mode)
    os.replace(tmp, path)
    return path
