"""Opening Zenoh sessions: the ``[zenoh]`` settings shared by the server and every client."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from sogm_service.wire.errors import SessionOpenError


class ZenohSettings(BaseModel):
    """The ``[zenoh]`` section: how a process opens its Zenoh session (strict, as every section)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    mode: Annotated[Literal["peer", "client", "router"], Field(
        description="The Zenoh mode: peer, client or router.")] = "peer"
    listen: Annotated[list[str], Field(description=(
        "Endpoints to listen on, e.g. [\"tcp/192.168.1.10:7447\"] for the site network. With "
        "none (nor connect, nor config_file) serve listens on tcp/127.0.0.1:7447, where "
        "clients connect by default."))] = []
    connect: Annotated[list[str], Field(description=(
        "Endpoints to connect to, e.g. [\"tcp/router.site.lan:7447\"]."))] = []
    config_file: Annotated[Path, Field(strict=False)] | None = Field(None, description=(
        "A full Zenoh JSON5 config (e.g. from sogm-service certs), honoured as it is: with it, "
        "set here only what should override it."), json_schema_extra={
        "example": "/etc/sogm-service/zenoh-server.json5"})
    multicast_scouting: Annotated[bool, Field(
        description="Find peers by UDP multicast scouting.")] = False


DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where ``serve`` listens and every client connects when told nothing else (loopback)."""

RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
"""How often a session asks its ``connect`` endpoints again once a link is gone.

Zenoh 1.x does the reconnecting itself: a client whose router (or peer) goes away keeps its
session, retries the ``connect`` endpoints with this backoff and, once linked again, declares
its publishers, subscribers and tokens anew (a peer does the same for its ``connect``
endpoints).  Zenoh's own backoff (1 s doubling to 4 s) leaves up to 4 s of a link that is
back unused after a drop-out of a few seconds; this one (0.25 s doubling to 1 s) at most 1 s,
for one TCP connection attempt a second while the link is down.  Opening still fails at once
when nothing answers (``connect/exit_on_failure`` stays Zenoh's: true for clients)."""


def make_config(settings: ZenohSettings) -> zenoh.Config:
    """A ``zenoh.Config``.  A JSON5 file (``config_file``) is honoured as it is, mode included:
    only the fields set explicitly beside it (listen, connect, mode, scouting) go on top.
    Without a file the settings' defaults apply (peer, multicast scouting off) and lost links
    are asked again with :data:`RECONNECT_RETRY`."""
    if settings.config_file is not None:
        config = zenoh.Config.from_file(str(settings.config_file))
        explicit = settings.model_fields_set
    else:
        config = zenoh.Config()
        explicit = {"mode", "multicast_scouting"}
    if "mode" in explicit:
        config.insert_json5("mode", json.dumps(settings.mode))
    if "multicast_scouting" in explicit:
        config.insert_json5("scouting/multicast/enabled",
                            json.dumps(settings.multicast_scouting))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.config_file is None:
        config.insert_json5("connect/retry", json.dumps(RECONNECT_RETRY))
    return config


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a session; the caller must ``close()`` it (an open session keeps the process alive).

    Raises :class:`~sogm_service.wire.errors.SessionOpenError` (one line, no Zenoh internals)
    when the config or an endpoint is unusable or nothing answers on a ``connect`` endpoint."""
    try:
        return zenoh.open(make_config(settings))
    except zenoh.ZError as exc:
        raise SessionOpenError(_session_error_text(settings, exc), "zenoh") from None


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/<host>:<port>`` endpoint on a port the OS just reported free (tests, demo)."""
    with socket.socket() as s:
        s.bind((host, 0))
        port = s.getsockname()[1]
    return f"tcp/{host}:{port}"


def wait_listening(endpoint: str, timeout: float, exited: Callable[[], bool],
                   log: Callable[[], str], poll_s: float = 0.02) -> None:
    """Wait until something accepts TCP connections on ``endpoint`` (``tcp/<host>:<port>``, or
    ``tls/...``: TLS listens on TCP too).

    ``exited`` tells whether the process expected to listen is gone (then this raises at once);
    ``log`` gives its output for the error.  Raises ``RuntimeError`` after ``timeout`` seconds.
    """
    host, port = endpoint.split("/", 1)[-1].rsplit(":", 1)  # tcp/ or tls/: the TCP port listens
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if exited():
            raise RuntimeError(f"the process exited before listening on {endpoint}:\n{log()}")
        with socket.socket() as s:
            if s.connect_ex((host, int(port))) == 0:
                return
        time.sleep(poll_s)
    raise RuntimeError(f"nothing listens on {endpoint} after {timeout:.0f} s:\n{log()}")


def loopback_settings(*, listen: str | None = None, connect: str | None = None,
                      mode: str = "peer") -> ZenohSettings:
    """Settings for a session on 127.0.0.1 only, multicast scouting off."""
    return ZenohSettings.model_validate({
        "mode": mode,
        "listen": [listen] if listen else [],
        "connect": [connect] if connect else [],
    })


ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial",
                      "vsock")


def check_endpoint(endpoint: str) -> str | None:
    """Why ``endpoint`` is not a Zenoh endpoint (``tcp/127.0.0.1:7447``), or ``None``."""
    proto, sep, address = endpoint.partition("/")
    if not sep:
        return (f"endpoint {endpoint!r} names no protocol: write tcp/{endpoint} "
                "(Zenoh endpoints are <protocol>/<address>)")
    if proto not in ENDPOINT_PROTOCOLS:
        return f"endpoint {endpoint!r}: unknown protocol {proto!r} (tcp, tls, udp, quic, ...)"
    if proto in ("tcp", "udp", "tls", "quic", "ws") and ":" not in address:
        return f"endpoint {endpoint!r} has no port: write {proto}/<host>:<port>"
    return None


def _session_error_text(settings: ZenohSettings, exc: Exception) -> str:
    for endpoint in [*settings.listen, *settings.connect]:
        why = check_endpoint(endpoint)
        if why is not None:
            return why
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if settings.connect and not settings.listen:
        return f"cannot connect to {', '.join(settings.connect)}: {first[:200]}"
    if settings.listen:
        return f"cannot listen on {', '.join(settings.listen)}: {first[:200]}"
    return f"cannot open a Zenoh session: {first[:200]}"
