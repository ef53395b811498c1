"""The dev PKI's certificates and its manifest (``pki.json``): the site CA, one EC P-256 key and
certificate per identity (common name = the identity's name), written with the ``cryptography``
library (no shelling out).  :mod:`sogm_service.apps.certs` builds the Zenoh configs and the
``certs`` command on top."""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import re
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROLES = ("server", "router", "robot", "viewer", "operator")
MANIFEST = "pki.json"
DEFAULT_ENDPOINT = "tls/localhost:7447"
DEFAULT_DAYS = 365
CA_DAYS = 3650
# The queryables a robot or viewer may ask (under <prefix>/<map>/).
READ_QUERIES = ("submap", "fused", "supercells", "info", "stats", "robots")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,62}$")
_RESERVED = {"ca", "pki"}


class PkiError(ValueError):
    """A refused PKI request; ``code`` is a short machine-readable reason."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


# --------------------------------------------------------------------------- certificates

@dataclass(frozen=True)
class CertificateAuthority:
    """A CA certificate and its private key."""

    cert: x509.Certificate
    key: ec.EllipticCurvePrivateKey


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _name(common_name: str, organization: str) -> x509.Name:
    return x509.Name([
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, organization),
        x509.NameAttribute(NameOID.COMMON_NAME, common_name),
    ])


def make_ca(common_name: str = "sogm-service dev CA", *, days: int = CA_DAYS,
            organization: str = "sogm-service site") -> CertificateAuthority:
    """A new self-signed CA (EC P-256), valid from one minute ago for ``days`` days."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(common_name, organization)
    start = _now() - dt.timedelta(minutes=1)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(start + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=True, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
            encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                       critical=False)
        .sign(key, hashes.SHA256())
    )
    return CertificateAuthority(cert, key)


def _san_entry(value: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(value))
    except ValueError:
        return x509.DNSName(value)


def make_identity(ca: CertificateAuthority, common_name: str, *, sans: Iterable[str] = (),
                  days: int = DEFAULT_DAYS, not_before: dt.datetime | None = None,
                  not_after: dt.datetime | None = None,
                  ) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A leaf certificate for ``common_name`` signed by ``ca``, with a new EC P-256 key.

    SANs: ``localhost``, ``127.0.0.1`` and ``sans`` (IP addresses where they parse as one, DNS
    names otherwise).  Valid for server and client authentication (each identity may be either
    end of a TLS link).  ``not_before``/``not_after`` override the validity (tests make expired
    certificates with them).
    """
    key = ec.generate_private_key(ec.SECP256R1())
    start = not_before if not_before is not None else _now() - dt.timedelta(minutes=1)
    end = not_after if not_after is not None else start + dt.timedelta(days=days)
    names: list[str] = []
    for s in ("localhost", "127.0.0.1", *sans):
        if s not in names:
            names.append(s)
    org = ca.cert.subject.get_attributes_for_oid(NameOID.ORGANIZATION_NAME)
    organization = str(org[0].value) if org else "sogm-service site"
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name, organization)).issuer_name(ca.cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=True, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=False, key_cert_sign=False, crl_sign=False,
            encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(x509.SubjectAlternativeName([_san_entry(s) for s in names]),
                       critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                       critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
            ca.key.public_key()), critical=False)
        .sign(ca.key, hashes.SHA256())
    )
    return cert, key


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by the owner only (created 0600, never wider)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.chmod(tmp, 0o600)
    os.replace(tmp, path)


def _write_public(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    _write_private(path, key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))


def write_cert(path: Path, cert: x509.Certificate) -> None:
    _write_public(path, cert.public_bytes(serialization.Encoding.PEM))


def load_ca(directory: Path) -> CertificateAuthority:
    cert = x509.load_pem_x509_certificate((directory / "ca.crt").read_bytes())
    key = serialization.load_pem_private_key((directory / "ca.key").read_bytes(), None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise PkiError("bad_ca_key", f"{directory / 'ca.key'} is not an EC private key")
    return CertificateAuthority(cert, key)


# --------------------------------------------------------------------------- manifest

@dataclass
class Pki:
    """What a PKI directory holds: its identities by role and the site's parameters."""

    directory: Path
    servers: list[str]
    robots: list[str] = field(default_factory=list)
    viewers: list[str] = field(default_factory=list)
    router: str | None = None
    endpoint: str = DEFAULT_ENDPOINT
    sans: list[str] = field(default_factory=list)
    map_name: str = "default"
    prefix: str = "sogm"
    days: int = DEFAULT_DAYS
    operators: list[str] = field(default_factory=list)  # viewers that may also drop layers

    def names(self) -> list[str]:
        return [*self.servers, *([self.router] if self.router else []),
                *self.robots, *self.viewers, *self.operators]

    def role(self, name: str) -> str:
        if name in self.servers:
            return "server"
        if name == self.router:
            return "router"
        if name in self.robots:
            return "robot"
        if name in self.viewers:
            return "viewer"
        if name in self.operators:
            return "operator"
        raise KeyError(name)

    def cert(self, name: str) -> Path:
        return self.directory / f"{name}.crt"

    def key(self, name: str) -> Path:
        return self.directory / f"{name}.key"

    def config(self, name: str) -> Path:
        """The Zenoh JSON5 config of identity ``name``."""
        return self.directory / f"{name}.json5"

    @property
    def ca_cert(self) -> Path:
        return self.directory / "ca.crt"

    @property
    def acl_holder(self) -> str:
        """The identity whose node carries the access control (router, else first server)."""
        return self.router if self.router else self.servers[0]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["directory"] = str(self.directory)
        return d

    @classmethod
    def load(cls, directory: Path) -> Pki:
        path = Path(directory).resolve() / MANIFEST
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError as e:
            raise PkiError("no_pki", f"{path} not found: run `certs init` first") from e
        except (OSError, ValueError) as e:
            raise PkiError("bad_manifest", f"{path}: {e}") from e
        if not isinstance(d, dict):
            raise PkiError("bad_manifest", f"{path}: not a JSON object")
        d["directory"] = Path(directory).resolve()
        try:
            return cls(**d)
        except TypeError as e:
            raise PkiError("bad_manifest", f"{path}: {e}") from e


def _check_name(name: str) -> None:
    if not _NAME_RE.match(name) or name.lower() in _RESERVED:
        raise PkiError("bad_name", f"{name!r}: an identity name is 1-63 letters, digits, "
                                   "'_', '.', '-' (not starting with a punctuation mark), and "
                                   "not 'ca' or 'pki'")


_SAN_RE = re.compile(r"^[A-Za-z0-9*][A-Za-z0-9.\-:*]{0,252}$")


def _check_san(san: str) -> None:
    if not _SAN_RE.match(san):
        raise PkiError("bad_san", f"{san!r}: a SAN is a DNS name or an IP address")


def _check_endpoint(endpoint: str) -> None:
    proto, sep, rest = endpoint.partition("/")
    if proto != "tls" or not sep or ":" not in rest:
        raise PkiError("bad_endpoint", f"{endpoint!r}: a TLS endpoint is tls/<host>:<port>")


def _check_map(map_name: str, prefix: str) -> None:
    if not re.match(r"^[A-Za-z0-9_\-]+$", map_name):
        raise PkiError("bad_map", f"{map_name!r}: a map name is letters, digits, '_', '-'")
    if not re.match(r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$", prefix.strip("/")):
        raise PkiError("bad_prefix", f"{prefix!r}: a prefix is chunks of letters, digits, "
                                     "'_', '-' separated by '/'")
