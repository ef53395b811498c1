"""sogm-service serve (the map server daemon) and sogm-service router (a Zenoh router).

The flags of serve that stand for config fields (--listen, --connect, --zenoh-config,
--storage, --ros2, --ros2-domain) are applied by one function, `apply_overrides`, through the
config's own validation, so a flag is checked exactly as the same field in a TOML file.
"""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import threading
from pathlib import Path
from typing import Any

from sogm_service.apps.logs import setup_logging
from sogm_service.apps.options import (
    UsageError,
    command,
    fail,
    require_extra,
    zenoh_config_arg,
)
from sogm_service.client.session import DEFAULT_ENDPOINT

DEFAULT_ROUTER_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_SERVE_LISTEN = DEFAULT_ENDPOINT  # where every client command connects by default

OVERRIDES: tuple[tuple[str, str, str], ...] = (
    ("listen", "zenoh", "listen"),
    ("connect", "zenoh", "connect"),
    ("zenoh_config", "zenoh", "config_file"),
    ("storage", "storage", "directory"),
    ("ros2", "ros2", "enabled"),
    ("ros2_domain", "ros2", "domain"),
)
"""serve's flags that override config fields: (flag's dest, section, field)."""


def add_parser(subparsers: Any) -> None:
    _add_serve(subparsers)
    _add_router(subparsers)


def _add_serve(subparsers: Any) -> None:
    p = command(subparsers, "serve", "run the map server daemon",
                epilog="example: sogm-service serve --config deploy/sogm-service.toml\n"
                       "Ctrl-C / SIGTERM: drain the queue, flush the store, exit 0.")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="TOML config (deploy/sogm-service.toml documents every field; "
                        "default: built-in defaults)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="Zenoh listen endpoint (repeatable; overrides the config; default "
                        f"{DEFAULT_SERVE_LISTEN} when the config names no endpoint)")
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="Zenoh connect endpoint, e.g. a router (repeatable; overrides the "
                        "config; default: the config's)")
    p.add_argument("--storage", type=Path, default=None, metavar="DIR",
                   help="tile store directory (default: the config's; none: in memory)")
    zenoh_config_arg(p)
    p.add_argument("--ros2", action="store_true", default=None,
                   help="serve ROS 2 robots and tools over rmw_zenoh ([ros2] enabled; "
                        "needs the ros2 extra)")
    p.add_argument("--ros2-domain", type=int, default=None, metavar="N",
                   help="ROS_DOMAIN_ID (default: the config's, 0)")
    p.set_defaults(handler=serve)


def _add_router(subparsers: Any) -> None:
    p = command(subparsers, "router", "run a Zenoh router (Python) for robots and servers")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint (repeatable; default {DEFAULT_ROUTER_LISTEN}: loopback "
                        "only, name the site address to open it)")
    p.add_argument("--config", "--zenoh-config", dest="config", type=Path, default=None,
                   metavar="FILE", help="Zenoh JSON5 config, honoured as is, its mode and "
                                        "listeners too (default: none)")
    p.set_defaults(handler=router)


def stop_on_signal() -> threading.Event:
    """An event set by SIGINT or SIGTERM; install it before opening any session so that an
    early signal still leads to a clean shutdown."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def wait_for(stop: threading.Event) -> None:
    while not stop.wait(0.2):
        pass


def apply_overrides(config: Any, args: argparse.Namespace) -> Any:
    """The config with every override flag given on the command line (`OVERRIDES`), each
    section validated as a whole; with no endpoint anywhere, it listens where the client
    commands connect by default."""
    if args.zenoh_config is not None and not args.zenoh_config.is_file():
        raise UsageError(f"--zenoh-config {args.zenoh_config}: no such file")
    sections: dict[str, dict[str, Any]] = {}
    for dest, section, field in OVERRIDES:
        value = getattr(args, dest)
        if value is not None and value is not False:  # not given: the config's value
            sections.setdefault(section, {})[field] = value
    z = config.zenoh
    if not (sections.get("zenoh") or z.listen or z.connect or z.config_file):
        sections["zenoh"] = {"listen": [DEFAULT_SERVE_LISTEN]}
    updates = {name: _section(config, name, fields) for name, fields in sections.items()}
    return config.model_copy(update=updates)


def _section(config: Any, name: str, fields: dict[str, Any]) -> Any:
    from pydantic import ValidationError

    current = getattr(config, name)
    try:
        return type(current).model_validate({**current.model_dump(), **fields})
    except ValidationError as exc:
        error = exc.errors()[0]
        field = error["loc"][0] if error["loc"] else ""
        dest = next((d for d, s, f in OVERRIDES if s == name and f == field), name)
        raise UsageError(f"--{dest.replace('_', '-')}: {error['msg']}") from None


def serve(args: argparse.Namespace) -> int:
    from sogm_service.client.session import check_endpoint
    from sogm_service.service.config import load_config

    config = load_config(args.config)  # ConfigError: one line (with the fields), exit 2
    if getattr(args, "log_level", None) is None:  # the config's level unless told
        setup_logging(config.log_level)
    config = apply_overrides(config, args)
    for endpoint in [*config.zenoh.listen, *config.zenoh.connect]:
        why = check_endpoint(endpoint)
        if why is not None:
            return fail("serve", why)
    if config.ros2.enabled:
        require_extra("ros2", "serve --ros2")
    return _run_server(config)


def _run_server(config: Any) -> int:
    from sogm_service.service.server.server import MapServer
    from sogm_service.wire.errors import StoreLockedError, StoreUnavailableError

    stop = stop_on_signal()
    server = MapServer(config)
    try:
        server.start()
    except StoreLockedError as exc:  # an operator's mistake: one line, no traceback
        server.stop()
        holder = f"pid {exc.pid}" if exc.pid is not None else "another process"
        return fail("serve", f"store {exc.directory} is locked by {holder}; one server per "
                             "store directory")
    except StoreUnavailableError as exc:  # an object store's endpoint, bucket or credentials
        server.stop()
        return fail("serve", exc.message)
    except BaseException:
        server.stop()
        raise
    # Everything imported and built so far lives as long as the process: keep it out of the
    # cyclic GC's full collections (~20 ms each with ~50k objects, a latency spike for
    # whichever query or ISM they interrupt).
    gc.collect()
    gc.freeze()
    where = config.zenoh.listen or config.zenoh.connect or [f"{config.zenoh.config_file}"]
    print(f"sogm-service: serving map {config.map.name!r} as {server.server_id} on "
          f"{', '.join(map(str, where))}", flush=True)
    try:
        wait_for(stop)
    finally:
        logging.getLogger("sogm_service").info("shutting down: draining and flushing")
        server.stop()
    return 0


def router(args: argparse.Namespace) -> int:
    from sogm_service.client.session import ZenohSettings, check_endpoint, open_session

    for endpoint in args.listen or []:
        why = check_endpoint(endpoint)
        if why is not None:
            return fail("router", why)
    if args.config is not None:  # the file as it is; --listen only when given
        if not args.config.is_file():
            return fail("router", f"--config {args.config}: no such file")
        extra = {"listen": args.listen} if args.listen else {}
        settings = ZenohSettings(config_file=args.config, **extra)
    else:
        settings = ZenohSettings(mode="router", listen=args.listen or [DEFAULT_ROUTER_LISTEN])
    stop = stop_on_signal()
    session = open_session(settings)
    where = settings.listen or f"the listeners of {args.config}"
    print(f"sogm-service router {session.info.zid()} listening on {where}", flush=True)
    try:
        wait_for(stop)
    finally:
        session.close()
    return 0

