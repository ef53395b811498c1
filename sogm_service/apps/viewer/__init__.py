"""sogm-service view: the live map in a browser (a separate process, another Zenoh client).

The viewer connects to a map server like any client (MapClient), serves one page (plain
JavaScript and a canvas, shipped in this package: it works offline) on loopback, and pushes
tile pictures, robot poses, tile events, ISM footprints and stats over a WebSocket.  The app
module keeps one slow browser from slowing anything else; the tiles module chooses which
pictures a view needs.

Starlette, uvicorn and websockets (the viewer extra) are imported only when the viewer runs,
so neither the rest of the package nor this command's help needs them.
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

from sogm_service.apps.options import (
    PROG,
    UsageError,
    command,
    fail,
    log_options,
    require_extra,
    standalone,
)

DEFAULT_HTTP = "127.0.0.1:8080"
_WS = "websockets-sansio"  # uvicorn's newer implementation on the websockets library
DESCRIPTION = "Serve a live view of a map in the browser (loopback only by default)."


def add_parser(subparsers: Any) -> None:
    p = command(subparsers, "view", "the live map viewer in the browser (loopback only by "
                                    "default; needs the viewer extra)", description=DESCRIPTION)
    _arguments(p)
    p.set_defaults(handler=run)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                   help="Zenoh endpoint of the map server or a router")
    p.add_argument("--http", default=DEFAULT_HTTP, metavar="HOST:PORT",
                   help="where the page is served (port 0: any free one)")
    p.add_argument("--map", default="default", help="map name")
    p.add_argument("--prefix", default="sogm", help="key prefix")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config used as is: TLS, certificates, access control "
                        "(default: none)")
    p.add_argument("--refresh", type=float, default=1.0, metavar="S",
                   help="seconds between refreshes of the visible tiles")
    p.add_argument("--poll", type=float, default=1.0, metavar="S",
                   help="seconds between info/stats polls")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="query timeout (s)")
    p.add_argument("--pose-key", default="pose/**", metavar="KEY", help="robot poses")
    p.add_argument("--ism-key", default="ism/**", metavar="KEY",
                   help="ISMs whose footprints are drawn ('' for none)")
    p.add_argument("--allow-host", action="append", default=[], metavar="HOST",
                   help="another Host name the page may be reached by, a reverse proxy's "
                        "(repeatable; default: none)")
    p.add_argument("--allow-non-loopback", action="store_true",
                   help="allow --http on an address other than loopback (no authentication: "
                        "put a TLS proxy with a login in front, or use an SSH tunnel instead)")
    p.add_argument("--open", action="store_true", help="open the page in a browser")
    p.add_argument("--keepout", default=None, metavar="A,B",
                   help="layers or class patterns of the keepout mask overlay (nav2's "
                        "KeepoutFilter, as [nav2] keepout; default: none)")
    p.add_argument("--keepout-threshold", type=float, default=0.6, metavar="P",
                   help="probability at or above which a cell is kept out (default 0.6)")
    p.add_argument("--speed", default=None, metavar="PATTERN=PERCENT,...",
                   help="layers or class patterns and their limits of the speed mask overlay "
                        "(as [nav2] speed; default: none)")
    p.add_argument("--speed-threshold", type=float, default=0.6, metavar="P",
                   help="probability at or above which a speed class applies (default 0.6)")


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
                             query_timeout_s=args.timeout, filters=_filters(args)))
    app = create_app(hub, refresh_s=args.refresh,
                     allowed_hosts=allowed_hosts(host, args.allow_host))
    verbose = getattr(args, "log_level", None) == "debug"
    config = uvicorn.Config(app, log_level="debug" if verbose else "warning",
                            ws=_WS if _WS in WS_PROTOCOLS else "websockets",
                            ws_max_size=64 * 1024, lifespan="on", timeout_graceful_shutdown=3)
    return uvicorn.Server(config)


def _prepare(args: argparse.Namespace) -> tuple[str, int]:
    """The host and port to listen on, or a UsageError."""
    try:
        host, port = parse_http(args.http)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not is_loopback(host) and not args.allow_non_loopback:
        raise UsageError(
            f"refusing to listen on {host}: the page has no login and shows the whole map. "
            "Reach it through an SSH tunnel (ssh -L 8080:127.0.0.1:8080 host) or pass "
            "--allow-non-loopback behind a TLS proxy with authentication.")
    if min(args.refresh, args.poll, args.timeout) <= 0:
        raise UsageError("--refresh, --poll and --timeout must be > 0")
    _filters(args)
    return host, port


def _filters(args: argparse.Namespace) -> Any:
    """The mask overlays of --keepout and --speed (a UsageError for a malformed one)."""
    from sogm_service.adapters.ros2.filters import spec_from_options

    try:
        return spec_from_options(args.keepout, args.keepout_threshold, args.speed,
                                 args.speed_threshold)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def start_viewer(argv: list[str]) -> RunningViewer:
    """Start a viewer (same options as the command) in a background thread: for ``demo
    --view``.  Returns once it listens; ``stop()`` it before the process ends."""
    parser = standalone(f"{PROG} view", DESCRIPTION)
    log_options(parser)
    _arguments(parser)
    args = parser.parse_args(argv)
    host, port = _prepare(args)
    server = _server(args, host)
    sock = _bind(host, port)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]},
                              name="viewer-http", daemon=True)
    thread.start()
    return RunningViewer(_url(host, sock), server, thread)


def main(argv: list[str] | None = None) -> int:
    """sogm-service view with these arguments: serve until SIGINT/SIGTERM."""
    from sogm_service.apps import cli

    return cli.main(["view", *(sys.argv[1:] if argv is None else argv)])


def run(args: argparse.Namespace) -> int:
    host, port = _prepare(args)
    require_extra("viewer", "view")
    server = _server(args, host)
    try:
        sock = _bind(host, port)
    except OSError as exc:
        return fail("view", f"cannot listen on {args.http}: {exc.strerror}")
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
