"""``sogm-service view``: the live map in a browser (a separate process, another Zenoh client).

The viewer connects to a map server like any client (:class:`~sogm_service.client.MapClient`),
serves one page (plain JavaScript and a canvas, shipped in this package: it works offline) on
loopback, and pushes tile pictures, robot poses, tile events, ISM footprints and stats over a
WebSocket.  See :mod:`.app` for how one slow browser is kept from slowing anything else, and
:mod:`.tiles` for which pictures a view needs.

Starlette, uvicorn and websockets are imported only here, so the rest of the package does not
need them.
"""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULT_HTTP = "127.0.0.1:8080"
_WS = "websockets-sansio"  # uvicorn's newer implementation on the websockets library
_MISSING = ("the viewer needs starlette, uvicorn and websockets: "
            "pip install 'sogm-service[viewer]'")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="sogm-service view",
        description="Serve a live view of a map in the browser (loopback only by default).")
    p.add_argument("--connect", default="tcp/127.0.0.1:7447",
                   help="Zenoh endpoint of the map server or a router (default %(default)s)")
    p.add_argument("--http", default=DEFAULT_HTTP,
                   help="HOST:PORT the page is served on (default %(default)s; port 0: any)")
    p.add_argument("--map", default="default", help="map name (default %(default)s)")
    p.add_argument("--prefix", default="sogm", help="key prefix (default %(default)s)")
    p.add_argument("--zenoh-config", type=Path, default=None,
                   help="Zenoh JSON5 config used as is (TLS, certificates, access control)")
    p.add_argument("--refresh", type=float, default=1.0,
                   help="seconds between refreshes of the visible tiles (default %(default)s)")
    p.add_argument("--poll", type=float, default=1.0,
                   help="seconds between info/stats polls (default %(default)s)")
    p.add_argument("--timeout", type=float, default=2.0, help="query timeout (s)")
    p.add_argument("--pose-key", default="pose/**", help="robot poses (default %(default)s)")
    p.add_argument("--ism-key", default="ism/**",
                   help="ISMs whose footprints are drawn (default %(default)s; '' for none)")
    p.add_argument("--allow-host", action="append", default=[],
                   help="another Host name the page may be reached by (a reverse proxy's)")
    p.add_argument("--allow-non-loopback", action="store_true",
                   help="allow --http on an address other than loopback (no authentication: "
                        "put a TLS proxy with a login in front, or use an SSH tunnel instead)")
    p.add_argument("--open", action="store_true", help="open the page in a browser")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def parse_http(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` too) -> host and port, or ``ValueError``."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(f"--http wants HOST:PORT, got {text!r}")
    host = host.strip("[]") or "127.0.0.1"
    return host, int(port_text)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def allowed_hosts(host: str, extra: list[str]) -> list[str]:
    """Host header values the page answers (DNS rebinding defence)."""
    names = {"localhost", "127.0.0.1", "::1", host, *extra}
    return sorted(n for n in names if n not in ("0.0.0.0", "::"))


@dataclass
class RunningViewer:
    """A viewer serving in a background thread (:func:`start_viewer`)."""

    url: str
    server: Any
    thread: threading.Thread

    def stop(self, timeout: float = 10.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout)


def _bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(64)
    sock.set_inheritable(True)
    return sock


def _url(host: str, sock: socket.socket) -> str:
    port = sock.getsockname()[1]
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


def _server(args: argparse.Namespace, host: str) -> Any:
    import uvicorn
    from uvicorn.config import WS_PROTOCOLS

    from sogm_service.apps.viewer.app import create_app
    from sogm_service.apps.viewer.hub import HubSettings, MapHub

    hub = MapHub(HubSettings(endpoint=args.connect, map_name=args.map, prefix=args.prefix,
                             zenoh_config=args.zenoh_config, pose_key=args.pose_key,
                             ism_key=args.ism_key or None, poll_s=args.poll,
                             query_timeout_s=args.timeout))
    app = create_app(hub, refresh_s=args.refresh,
                     allowed_hosts=allowed_hosts(host, args.allow_host))
    config = uvicorn.Config(app, log_level="debug" if args.verbose else "warning",
                            ws=_WS if _WS in WS_PROTOCOLS else "websockets",
                            ws_max_size=64 * 1024, lifespan="on", timeout_graceful_shutdown=3)
    return uvicorn.Server(config)


def _prepare(argv: list[str] | None) -> tuple[argparse.Namespace, str, int]:
    args = build_parser().parse_args(argv)
    try:
        host, port = parse_http(args.http)
    except ValueError as exc:
        raise SystemExit(f"sogm-service view: {exc}") from None
    if not is_loopback(host) and not args.allow_non_loopback:
        raise SystemExit(
            f"sogm-service view: refusing to listen on {host}: the page has no login and shows "
            "the whole map. Reach it through an SSH tunnel (ssh -L 8080:127.0.0.1:8080 host) "
            "or pass --allow-non-loopback behind a TLS proxy with authentication.")
    if min(args.refresh, args.poll, args.timeout) <= 0:
        raise SystemExit("sogm-service view: --refresh, --poll and --timeout must be > 0")
    return args, host, port


def start_viewer(argv: list[str]) -> RunningViewer:
    """Start a viewer (same options as the command) in a background thread: for ``demo
    --view``.  Returns once it listens; ``stop()`` it before the process ends."""
    args, host, port = _prepare(argv)
    server = _server(args, host)
    sock = _bind(host, port)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]},
                              name="viewer-http", daemon=True)
    thread.start()
    return RunningViewer(_url(host, sock), server, thread)


def main(argv: list[str] | None = None) -> int:
    """``sogm-service view``: serve until SIGINT/SIGTERM; returns the exit code."""
    from sogm_service.apps.logs import setup_logging

    try:
        args, host, port = _prepare(argv)
    except SystemExit as exc:
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
            return 2
        raise
    setup_logging("debug" if args.verbose else "info")
    try:
        server = _server(args, host)
    except ImportError as exc:
        print(f"sogm-service view: {_MISSING} ({exc})", file=sys.stderr)
        return 2
    try:
        sock = _bind(host, port)
    except OSError as exc:
        print(f"sogm-service view: cannot listen on {args.http}: {exc.strerror}",
              file=sys.stderr)
        return 2
    url = _url(host, sock)
    print(f"sogm-service view: {url} (map {args.map!r} at {args.connect})", flush=True)
    if not is_loopback(host):
        print("sogm-service view: WARNING: listening beyond loopback without authentication",
              file=sys.stderr, flush=True)
    if args.open:
        import webbrowser

        webbrowser.open(url)
    server.run(sockets=[sock])
    return 0
