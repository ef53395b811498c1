"""How the bench's sessions reach each other: plain TCP on loopback, or a site's Zenoh configs.

``sogm-service bench --zenoh-config CLIENT [--server-zenoh-config SERVER]`` (or ``--secure``,
a fresh dev PKI made by :func:`sogm_service.apps.certs.init_pki`) runs the Zenoh rows through
those configs, so an operator can measure what TLS, mutual authentication and access control
cost on their own set-up:

* the *client side* (the query client, the publishing robots, the paced fleet) opens every
  session with ``CLIENT``; the processes that stand in for a server (``serve``, the raw
  queryable and the counting subscriber of the baselines, the start-up observer) with
  ``SERVER``.  Both are honoured as they are (mode, TLS, access control, scouting) except for
  their endpoints: the bench starts several servers side by side, each on an ephemeral port of
  the server config's protocol on 127.0.0.1, and points the clients at the one being measured.
* Under access control a robot may put only on ``ism/<its name>/**``: the bench publishes as
  the common name of ``CLIENT``'s certificate (``bench`` without one).

Without flags everything is plain TCP on 127.0.0.1, multicast scouting off.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

from sogm_service.client.session import free_tcp_endpoint, loopback_settings
from sogm_service.service.config import ZenohSettings

DEFAULT_ROBOT = "bench"


@dataclass(frozen=True)
class Transport:
    """The configs of the two sides (``None``: plain loopback TCP) and the robot name."""

    client_config: Path | None = None
    server_config: Path | None = None
    robot: str = DEFAULT_ROBOT
    protocol: str = "tcp"

    def endpoint(self) -> str:
        """A fresh endpoint for one server: the server config's protocol, 127.0.0.1."""
        return free_tcp_endpoint().replace("tcp/", f"{self.protocol}/", 1)

    def client(self, connect: str) -> ZenohSettings:
        """Settings of a client session that connects to ``connect``."""
        if self.client_config is None:
            return loopback_settings(connect=connect, mode="client")
        return ZenohSettings.model_validate({"config_file": self.client_config,
                                             "connect": [connect]})

    def server(self, listen: str, connect: str | None = None) -> ZenohSettings:
        """Settings of a session standing in for a server, listening on ``listen``."""
        if self.server_config is None:
            return loopback_settings(listen=listen, connect=connect)
        return ZenohSettings.model_validate({"config_file": self.server_config,
                                             "listen": [listen],
                                             "connect": [connect] if connect else []})

    def client_args(self) -> list[str]:
        """``--zenoh-config FILE`` for a helper process on the client side (or nothing)."""
        return ["--zenoh-config", str(self.client_config)] if self.client_config else []

    def server_args(self) -> list[str]:
        return ["--zenoh-config", str(self.server_config)] if self.server_config else []

    def server_toml(self) -> str:
        """The ``config_file`` line of a ``[zenoh]`` section for ``serve`` (or nothing)."""
        return f"config_file = {json.dumps(str(self.server_config))}\n" \
            if self.server_config else ""

    def ism_key(self, topic: str) -> str:
        """``ism/<robot>/<topic>``: a key this bench's robot identity may put on."""
        return f"ism/{self.robot}/{topic}"

    def describe(self) -> str:
        if self.client_config is None and self.server_config is None:
            return "tcp on 127.0.0.1"
        return (f"{self.protocol} on 127.0.0.1; client config {self.client_config}, server "
                f"config {self.server_config or '(plain serve)'}; publishing as {self.robot!r}")


_PLAIN = Transport()
_CURRENT: ContextVar[Transport | None] = ContextVar("sogm_bench_transport", default=None)


def current() -> Transport:
    """The transport of the run in progress (plain loopback TCP unless told otherwise)."""
    return _CURRENT.get() or _PLAIN


@contextmanager
def using(transport: Transport) -> Iterator[Transport]:
    token = _CURRENT.set(transport)
    try:
        yield transport
    finally:
        _CURRENT.reset(token)


def from_files(client_config: Path | None, server_config: Path | None) -> Transport:
    """A transport from two Zenoh config files (either may be ``None``); raises ``ValueError``
    with one line when a file is missing or is not a Zenoh config."""
    for flag, path in (("--zenoh-config", client_config),
                       ("--server-zenoh-config", server_config)):
        if path is not None and not path.is_file():
            raise ValueError(f"{flag} {path}: no such file")
    listen = _field(server_config, "listen/endpoints") if server_config else None
    if isinstance(listen, dict):  # per mode: {"router": [...], "peer": [...]}
        listen = [e for v in listen.values() for e in (v or [])]
    protocol = str(listen[0]).split("/", 1)[0] if isinstance(listen, list) and listen else "tcp"
    cert = _field(client_config, "transport/link/tls/connect_certificate") \
        if client_config else None
    return Transport(client_config, server_config, _common_name(cert) or DEFAULT_ROBOT,
                     protocol)


def _field(path: Path, key: str) -> object:
    """One field of a Zenoh config file (as JSON), ``None`` when unset."""
    import zenoh

    try:
        config = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        first = (str(exc).strip().splitlines() or ["unreadable"])[0]
        raise ValueError(f"{path}: not a Zenoh config: {first[:200]}") from None
    try:
        value: object = json.loads(config.get_json(key))
    except zenoh.ZError:
        return None
    return value


def _common_name(cert: object) -> str | None:
    """The common name of the client certificate, which access control keys robots by."""
    if not isinstance(cert, str) or not Path(cert).is_file():
        return None
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    subject = x509.load_pem_x509_certificate(Path(cert).read_bytes()).subject
    names = subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else None
