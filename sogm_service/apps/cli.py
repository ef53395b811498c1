"""The ``sogm-service`` command (argparse: help text, unit and default on every option).

Heavy modules (zenoh, numba kernels, the simulator) are imported only by the subcommand that
needs them, so ``serve`` starts fast.  Subcommands owned by other modules (``tiles``, ``eval``,
``demo``, ...) get the rest of the command line and build their own parser; the logging options
(``-v``, ``-q``, ``--log-level``) are taken out of it first, so they work everywhere.

Every mistake a person can make (no server, a bad endpoint, a file that is not a grid, a store
in use, a config that does not validate, an ISM the server rejects) ends in one line on stderr
and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import math
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sogm_service.apps.logs import setup_logging
from sogm_service.client.session import DEFAULT_ENDPOINT
from sogm_service.wire.errors import ClientError, SogmError

EXIT_USAGE = 2
"""Exit status of every refusal: bad arguments, config, input, or what the server refused."""


# Subcommands that parse their own options.  Each is imported only when it runs (so ``serve``
# starts fast), through a plain function that tools and mypy can follow.
def _tiles(argv: list[str]) -> int:
    from sogm_service.apps import tiletool

    return tiletool.main(argv)


def _eval(argv: list[str]) -> int:
    if argv[:1] == ["matching"]:
        from sogm_service.eval import matching

        return matching.main(argv[1:])
    from sogm_service.eval import segmentation

    return segmentation.main(argv)


def _demo(argv: list[str]) -> int:
    from sogm_service.apps import demo

    return demo.main(argv)


def _replay(argv: list[str]) -> int:
    from sogm_service.apps import replay

    return replay.main(argv)


def _certs(argv: list[str]) -> int:
    from sogm_service.apps import certs

    return certs.main(argv)


def _export(argv: list[str]) -> int:
    from sogm_service.apps import nav2tool

    return nav2tool.export_main(argv)


def _import(argv: list[str]) -> int:
    from sogm_service.apps import nav2tool

    return nav2tool.import_main(argv)


def _view(argv: list[str]) -> int:
    from sogm_service.apps import viewer

    return viewer.main(argv)


def _bench(argv: list[str]) -> int:
    from sogm_service import bench
    from sogm_service.apps.certs import bench_pki

    return bench.main(argv, dev_pki=bench_pki)


_DELEGATED: dict[str, tuple[Callable[[list[str]], int], str]] = {
    "tiles": (_tiles, "list, export and import stored tiles"),
    "eval": (_eval, "evaluations: eval supercells (the paper's, SEVDS vs SEEDS/SLIC/SLICO/"
                     "LSC), eval matching (scan matching on the Intel log)"),
    "demo": (_demo, "embedded demo: a server and a simulated fleet on 127.0.0.1"),
    "replay": (_replay, "replay a CARMEN laser log into a map"),
    "bench": (_bench, "the performance suite"),
    "view": (_view, "the live map viewer in the browser (loopback only by default)"),
    "certs": (_certs, "a dev PKI and mutual-TLS / access-control Zenoh configs"),
    "export": (_export, "export nav2 --out DIR: map.yaml + map.pgm for nav2's map_server"),
    "import": (_import, "import nav2 map.yaml --layer NAME: fuse a nav2 map as a prior"),
}

DEFAULT_ROUTER_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_SERVE_LISTEN = DEFAULT_ENDPOINT  # where every client command connects by default
LOG_LEVELS = ("debug", "info", "warning", "error")


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults shown after every option's help; descriptions and epilogs kept as written."""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sogm-service")
    except PackageNotFoundError:
        return "unknown"


def _log_options(p: argparse.ArgumentParser, top: bool = False) -> None:
    """-v / -q / --log-level.  SUPPRESS: given before or after the subcommand, the last wins
    and an absent one never overwrites one given earlier."""
    g = p.add_argument_group("logging")
    g.add_argument("-v", "--verbose", dest="log_level", action="store_const", const="debug",
                   default=argparse.SUPPRESS, help="debug logging (= --log-level debug)")
    g.add_argument("-q", "--quiet", dest="log_level", action="store_const", const="warning",
                   default=argparse.SUPPRESS, help="warnings and errors only")
    g.add_argument("--log-level", dest="log_level", choices=LOG_LEVELS,
                   default=argparse.SUPPRESS,
                   help="log level (default: the config's log_level for serve, else info)")
    if top:
        p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")


def _sub(sub: Any, name: str, help_text: str, description: str = "",
         epilog: str = "") -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        name, help=help_text, description=description or help_text, epilog=epilog,
        formatter_class=_Formatter)
    _log_options(p)
    return p


def _angle_options(p: argparse.ArgumentParser, what: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--yaw-deg", type=float, default=None, metavar="DEG",
                   help=f"{what} heading in degrees, counter-clockwise from the map's x axis "
                        "(default 0)")
    g.add_argument("--yaw", type=float, default=None, metavar="RAD",
                   help=f"{what} heading in RADIANS (kept for scripts; |yaw| > 2 pi is refused "
                        "as a likely degree value: use --yaw-deg)")


def _window_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("window (map frame)")
    g.add_argument("--x", type=float, default=0.0, metavar="M", help="window centre x (m)")
    g.add_argument("--y", type=float, default=0.0, metavar="M", help="window centre y (m)")
    _angle_options(g, "window")  # type: ignore[arg-type]
    g.add_argument("--width", type=float, default=10.0, metavar="M", help="window width (m)")
    g.add_argument("--height", type=float, default=10.0, metavar="M",
                   help="window height (m)")
    g.add_argument("--resolution", type=float, default=None, metavar="M",
                   help="cell size of the answer (m; default: the map's)")
    g.add_argument("--layers", default=None, metavar="A,B",
                   help="comma-separated layers (default: all)")
    g.add_argument("--interp", default="biodds", choices=["biodds", "bilinear", "nearest"],
                   help="resampling: biodds (the paper's Eq. 3-5: bilinear in log-odds), "
                        "bilinear (in probability), nearest")


def _connection_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("connection")
    g.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                   help="Zenoh endpoint of the server or a router (<protocol>/<host>:<port>)")
    g.add_argument("--map", default="default", help="map name")
    g.add_argument("--prefix", default="sogm", help="key prefix of the map's keys")
    g.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="query timeout (s; default 5, supercells 90: the first query after "
                        "an install may wait for the server to compile its kernels)")
    _zenoh_config_arg(g)  # type: ignore[arg-type]


def _zenoh_config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config, honoured as is (mode, TLS, endpoints), e.g. one "
                        "written by 'sogm-service certs'; replaces --connect")


def _output_args(p: argparse.ArgumentParser, grid: bool) -> None:
    g = p.add_argument_group("output")
    g.add_argument("--json", action="store_true",
                   help="print the result as one JSON object (for scripts) instead of text")
    if grid:
        g.add_argument("--png", type=Path, default=None, metavar="FILE",
                       help="write a picture (legend, scale bar in m, map axes; at least "
                            "512 px); several layers: one FILE_<layer>.png each")
        g.add_argument("--npy", type=Path, default=None, metavar="FILE",
                       help="write the array (layers, rows, cols) in the reply's encoding")
        g.add_argument("--encoding", default="prob_f32",
                       choices=["prob_u8", "prob_f32", "logodds_i16", "occupancy_i8",
                                "prob_u8_v2"],
                       help="cell encoding of the reply (and of --npy): probabilities as "
                            "float32 or 0..255, log-odds in 1/1000 nat, nav_msgs 0..100/-1, "
                            "or prob_u8_v2 (255 = unknown)")


QUERY_EPILOG = """examples:
  sogm-service query submap --x 2 --y 1 --yaw-deg 30 --width 6 --height 4 --png sub.png
  sogm-service query fused --method max --width 20 --height 20 --json
  sogm-service query supercells --x 2 --y 2 --width 6.4 --height 6.4 --png graph.png
  sogm-service query info
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sogm-service", formatter_class=_Formatter,
        description="Semantical occupancy grid map server on Zenoh.",
        epilog="Every command takes -v/-q/--log-level; 'sogm-service COMMAND -h' for its "
               "options.  Mistakes end with one line on stderr and exit status 2.")
    _log_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = _sub(sub, "serve", "run the map server daemon",
                 epilog="example: sogm-service serve --config deploy/sogm-service.toml\n"
                        "Ctrl-C / SIGTERM: drain the queue, flush the store, exit 0.")
    serve.add_argument("--config", type=Path, default=None, metavar="FILE",
                       help="TOML config (deploy/sogm-service.toml documents every field; "
                            "default: built-in defaults)")
    serve.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                       help="Zenoh listen endpoint (repeatable; overrides the config; default "
                            f"{DEFAULT_SERVE_LISTEN} when the config names no endpoint)")
    serve.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                       help="Zenoh connect endpoint, e.g. a router (repeatable; overrides the "
                            "config)")
    serve.add_argument("--storage", type=Path, default=None, metavar="DIR",
                       help="tile store directory (default: the config's; none: in memory)")
    _zenoh_config_arg(serve)
    serve.add_argument("--ros2", action="store_true",
                       help="serve ROS 2 robots and tools over rmw_zenoh ([ros2] enabled; "
                            "needs the ros2 extra)")
    serve.add_argument("--ros2-domain", type=int, default=None, metavar="N",
                       help="ROS_DOMAIN_ID (default: the config's, 0)")

    query = _sub(sub, "query", "query a running server", epilog=QUERY_EPILOG)
    qsub = query.add_subparsers(dest="what", required=True, metavar="WHAT")
    texts = {"submap": "the chosen layers resampled into a window (any pose and resolution)",
             "fused": "Eq. 6 over the chosen layers: bayes (P_B) or max (P_M)",
             "supercells": "the SEVDS topometric graph of a window (paper III-D.2)"}
    for name, text in texts.items():
        q = _sub(qsub, name, text, epilog=QUERY_EPILOG)
        _connection_args(q)
        _window_args(q)
        _output_args(q, grid=True)
        if name == "fused":
            q.add_argument("--method", default="bayes", choices=["bayes", "max"],
                           help="bayes: super-Bayesian sum of log-odds (P_B); max: the most "
                                "occupied layer per cell (P_M)")
        if name == "supercells":
            g = q.add_argument_group("SEVDS parameters (paper Eq. 7-10)")
            g.add_argument("--block-size", type=int, default=8, metavar="CELLS",
                           help="edge of the initial square supercells (cells)")
            g.add_argument("--levels", type=int, default=3,
                           help="block levels (each halves the block) before cell moves")
            g.add_argument("--bins", type=int, default=5,
                           help="histogram bins per layer (probability quantisation)")
            g.add_argument("--iterations", type=int, default=4,
                           help="cell-level sweeps")
            g.add_argument("--gamma", type=float, default=0.01,
                           help="weight of the boundary term (smoother borders when larger)")
            g.add_argument("--criterion", default="distribution",
                           choices=["distribution", "energy"],
                           help="distribution: summed histogram variance (SEVDS); energy: "
                                "SEEDS's histogram energy")
    for name, text in (("info", "the map: frame, resolution, layers, tiles, bounds"),
                       ("stats", "counters, rejections per reason, queue, latencies")):
        q = _sub(qsub, name, text)
        _connection_args(q)
        q.add_argument("--json", action="store_true",
                       help="print JSON (the default for info and stats; accepted for "
                            "symmetry)")

    pub = _sub(sub, "publish-ism", "send an ISM from a .npy or image file and wait until "
                                   "the server fused it",
               epilog="example: sogm-service publish-ism scan.npy --key "
                      "ism/robot1/laser/obstacle --resolution 0.05 --x 1 --y 2 --yaw-deg 90\n"
                      "Exit 0: fused (a query now sees it).  Exit 2: the server's reason, "
                      "or nothing heard back.")
    _connection_args(pub)
    pub.add_argument("file", type=Path,
                     help=".npy of 2-D uint8 (prob_u8), int8 (occupancy_i8) or float32 "
                          "(prob_f32) cells, row 0 at the map's lowest y; or an image (grey: "
                          "dark = occupied, row 0 at the top)")
    pub.add_argument("--key", default="ism/cli/manual",
                     help="key to publish on: ism/<robot>/<sensor>/<class>")
    pub.add_argument("--resolution", type=float, required=True, metavar="M",
                     help="ISM cell size (m), required")
    pub.add_argument("--x", type=float, default=0.0, metavar="M",
                     help="x of the corner of cell (0, 0) in the map frame (m)")
    pub.add_argument("--y", type=float, default=0.0, metavar="M",
                     help="y of the corner of cell (0, 0) in the map frame (m)")
    _angle_options(pub, "grid")
    pub.add_argument("--encoding", default=None,
                     choices=["prob_u8", "occupancy_i8", "prob_f32", "prob_u8_v2"],
                     help="cell encoding (default: from the dtype)")
    pub.add_argument("--layer", default=None,
                     help="layer name (default: the key after ism/, e.g. robot1/laser/obstacle)")
    pub.add_argument("--frame", default="map", help="frame of the pose (must be the map's)")
    pub.add_argument("--no-wait", action="store_true",
                     help="do not wait for the server's acknowledgement (fire and forget)")
    pub.add_argument("--wait-timeout", type=float, default=15.0, metavar="S",
                     help="how long to wait until the ISM is fused (s)")

    schemas = _sub(sub, "schemas", "write the JSON Schema of every message")
    schemas.add_argument("--out", type=Path, default=Path("schemas"), metavar="DIR",
                         help="directory of the *.json files")
    schemas.add_argument("--check", action="store_true",
                         help="write nothing; exit 1 if the files differ from the models")

    router = _sub(sub, "router", "run a Zenoh router (Python) for robots and servers")
    router.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                        help=f"endpoint (repeatable; default {DEFAULT_ROUTER_LISTEN}: loopback "
                             "only, name the site address to open it)")
    router.add_argument("--config", "--zenoh-config", dest="config", type=Path, default=None,
                        metavar="FILE", help="Zenoh JSON5 config, honoured as is (its mode "
                                             "and listeners too)")

    for name, (_, text) in _DELEGATED.items():
        d = sub.add_parser(name, help=text + " (own options: COMMAND -h)", add_help=False)
        d.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


# Processes that fuse or sample for long: their large temporaries are kept on the heap
# (:mod:`sogm_service.service.server.allocator`), which the short-lived commands do not need.
_LONG_RUNNING = frozenset({"serve", "demo", "replay", "bench"})


def _pop_log_options(argv: list[str], quiet: tuple[str, ...] = ("-q",)
                     ) -> tuple[list[str], str | None]:
    """Take -v/-q/--log-level out of a delegated command's arguments; the last one wins.
    ``--quiet`` stays with the command (demo's and eval's mean "no progress bar")."""
    rest: list[str] = []
    level: str | None = None
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in ("-v", "--verbose"):
            level = "debug"
        elif a in quiet:
            level = "warning"
        elif a == "--log-level" and i + 1 < len(argv) and argv[i + 1] in LOG_LEVELS:
            level = argv[i + 1]
            i += 1
        elif a.startswith("--log-level=") and a.split("=", 1)[1] in LOG_LEVELS:
            level = a.split("=", 1)[1]
        elif a == "--":
            rest += argv[i:]
            break
        else:
            rest.append(a)
        i += 1
    return rest, level


def _command_of(argv: list[str]) -> tuple[int, str | None]:
    """Index and name of the subcommand (after global logging options), if any."""
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in ("-v", "--verbose", "-q", "--quiet") or a.startswith("--log-level="):
            i += 1
        elif a == "--log-level":
            i += 2
        else:
            return i, a
    return i, None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    at, command = _command_of(argv)
    if command in _LONG_RUNNING:
        from sogm_service.service.server.allocator import keep_large_allocations

        keep_large_allocations()
    try:
        if command in _DELEGATED:  # they parse their own options (including -h)
            _, head = _pop_log_options(argv[:at], quiet=("-q", "--quiet"))
            rest, level = _pop_log_options(argv[at + 1:])
            setup_logging(level or head or "info")
            return _DELEGATED[command][0](rest)
        args = build_parser().parse_args(argv)
        level = getattr(args, "log_level", None)
        setup_logging(level or "info")
        handler = {"serve": _serve, "query": _query, "publish-ism": _publish_ism,
                   "schemas": _schemas, "router": _router}[args.command]
        return handler(args)
    except (SogmError, ClientError) as exc:
        print(f"sogm-service {command or ''}: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"sogm-service {command or ''}: interrupted", file=sys.stderr)
        return 130


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split()) if len(text) < 2000 else text[:2000]


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


def _fail(command: str, message: str) -> int:
    print(f"sogm-service {command}: {message}", file=sys.stderr)
    return EXIT_USAGE


def _serve(args: argparse.Namespace) -> int:
    from sogm_service.client.session import check_endpoint
    from sogm_service.service.config import load_config

    config = load_config(args.config)  # ConfigError: one line (with the fields), exit 2
    if getattr(args, "log_level", None) is None:  # the config's level unless told
        setup_logging(config.log_level)
    updates: dict[str, Any] = {}
    if args.listen:
        updates["listen"] = args.listen
    if args.connect:
        updates["connect"] = args.connect
    if args.zenoh_config:
        if not args.zenoh_config.is_file():
            return _fail("serve", f"--zenoh-config {args.zenoh_config}: no such file")
        updates["config_file"] = args.zenoh_config
    z = config.zenoh
    if not (updates or z.listen or z.connect or z.config_file):  # meet the clients' default
        updates["listen"] = [DEFAULT_SERVE_LISTEN]
    if updates:
        config = config.model_copy(update={"zenoh": config.zenoh.model_copy(update=updates)})
    for endpoint in [*config.zenoh.listen, *config.zenoh.connect]:
        why = check_endpoint(endpoint)
        if why is not None:
            return _fail("serve", why)
    if args.storage:
        config = config.model_copy(
            update={"storage": config.storage.model_copy(update={"directory": args.storage})})
    ros2: dict[str, Any] = {"enabled": True} if args.ros2 else {}
    if args.ros2_domain is not None:
        ros2["domain"] = args.ros2_domain
    if ros2:
        from pydantic import ValidationError

        from sogm_service.service.config import Ros2Settings

        try:
            section = Ros2Settings.model_validate({**config.ros2.model_dump(), **ros2})
        except ValidationError as exc:
            return _fail("serve", f"--ros2-domain: {exc.errors()[0]['msg']}")
        config = config.model_copy(update={"ros2": section})
    from sogm_service.service.server.server import MapServer
    from sogm_service.wire.errors import StoreLockedError

    stop = stop_on_signal()
    server = MapServer(config)
    try:
        server.start()
    except StoreLockedError as exc:  # an operator's mistake: one line, no traceback
        server.stop()
        print(f"sogm-service serve: store {exc.directory} is locked by "
              f"{'pid ' + str(exc.pid) if exc.pid is not None else 'another process'}; "
              "one server per store directory", file=sys.stderr)
        return 2
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


def _client(args: argparse.Namespace) -> Any:
    from sogm_service.client.mapclient import DEFAULT_TIMEOUT_S, MapClient

    if args.zenoh_config is not None and not args.zenoh_config.is_file():
        raise _usage(f"--zenoh-config {args.zenoh_config}: no such file")
    client = MapClient.connect(args.connect, map_name=args.map, prefix=args.prefix,
                               timeout=args.timeout or DEFAULT_TIMEOUT_S,
                               zenoh_config=args.zenoh_config)
    if args.timeout:
        client.supercells_timeout = args.timeout
    return client


def _usage(message: str) -> ClientError:
    return ClientError(message)


def _yaw(args: argparse.Namespace) -> float:
    if args.yaw_deg is not None:
        if not math.isfinite(args.yaw_deg):
            raise _usage("--yaw-deg must be finite")
        return math.radians(args.yaw_deg)
    yaw = 0.0 if args.yaw is None else float(args.yaw)
    if not math.isfinite(yaw) or abs(yaw) > 2 * math.pi + 1e-9:
        raise _usage(f"--yaw {args.yaw} is in radians and beyond one turn: did you mean "
                     f"--yaw-deg {args.yaw}?")
    return yaw


def _query(args: argparse.Namespace) -> int:
    # A bad --yaw is refused before anything is asked (or connected to).
    window = _window(args) if args.what not in ("info", "stats") else {}
    with _client(args) as client:
        return _run_query(client, args, window)


def _window(args: argparse.Namespace) -> dict[str, Any]:
    layers = args.layers.split(",") if args.layers else None
    return dict(x=args.x, y=args.y, yaw=_yaw(args), width=args.width, height=args.height,
                resolution=args.resolution, layers=layers, interp=args.interp)


def _run_query(client: Any, args: argparse.Namespace, window: dict[str, Any]) -> int:
    if args.what in ("info", "stats"):
        reply = client.info() if args.what == "info" else client.stats()
        print(reply.model_dump_json(indent=2))
        return 0
    if args.what == "supercells":
        return _run_supercells(client, args, window)
    if args.what == "submap":
        result = client.submap(**window, encoding=args.encoding)
    else:
        result = client.fused(method=args.method, **window, encoding=args.encoding)
    written = _write_grid_outputs(result, args.png, args.npy)
    _print_grid(result, args.json, written)
    return 0


def _run_supercells(client: Any, args: argparse.Namespace, window: dict[str, Any]) -> int:
    reply = client.supercells(**window, block_size=args.block_size, levels=args.levels,
                              bins=args.bins, iterations=args.iterations, gamma=args.gamma,
                              criterion=args.criterion, labels=args.png is not None)
    edges = sum(len(n.neighbors) for n in reply.nodes) // 2
    written: list[str] = []
    if args.npy is not None:
        import numpy as np

        np.save(args.npy, np.array([[n.x, n.y, *n.mean_probability] for n in reply.nodes]))
        written.append(str(args.npy))
    if args.png is not None:
        from sogm_service.apps.render import save_graph_png

        window.pop("layers", None)
        fused = client.fused(method="max", **window, layers=reply.layers, encoding="prob_f32")
        save_graph_png(args.png, reply, fused)
        written.append(str(args.png))
    if args.json:
        print(json.dumps({
            "kind": "supercells", "nodes": [n.model_dump() for n in reply.nodes],
            "edges": edges, "width": reply.width, "height": reply.height,
            "resolution": reply.resolution, "layers": list(reply.layers),
            "origin": reply.origin.model_dump(), "written": written}))
        return 0
    print(f"supercells: {len(reply.nodes)} nodes, {edges} edges over {reply.width}x"
          f"{reply.height} cells at {reply.resolution} m, layers {reply.layers}")
    for node in reply.nodes[:5]:
        print(f"  #{node.id}: ({node.x:.2f}, {node.y:.2f}) m, {node.area_m2:.2f} m2, "
              f"mean P {[round(p, 2) for p in node.mean_probability]}")
    for path in written:
        print(f"wrote {path}")
    return 0


def _print_grid(result: Any, as_json: bool, written: list[str]) -> None:
    g = result.geometry
    p = result.probabilities()
    known = float((abs(p - 0.5) > 1e-3).mean())
    occupied = float((p > 0.5 + 1e-3).mean())
    if as_json:
        print(json.dumps({
            "kind": "fused" if result.method else "submap", "method": result.method,
            "width": g.width, "height": g.height, "resolution": g.resolution,
            "origin": {"x": g.origin.x, "y": g.origin.y, "yaw": g.origin.yaw},
            "layers": list(result.layers), "encoding": result.encoding,
            "known_fraction": round(known, 6), "occupied_fraction": round(occupied, 6),
            "stamp": result.stamp, "written": written}))
        return
    print(f"{'fused (' + result.method + ')' if result.method else 'submap'}: "
          f"{g.width}x{g.height} cells at {g.resolution} m, origin ({g.origin.x:.3f}, "
          f"{g.origin.y:.3f}, {math.degrees(g.origin.yaw):.1f} deg), layers {result.layers}")
    print(f"known cells: {known * 100:.1f} %, occupied (p > 0.5): {occupied * 100:.1f} %")
    if known == 0.0:
        print("note: no cell of this window has been observed (is it inside the map? "
              "'sogm-service query info' gives the bounds)", file=sys.stderr)
    for path in written:
        print(f"wrote {path}")


def _write_grid_outputs(result: Any, png: Path | None, npy: Path | None) -> list[str]:
    written: list[str] = []
    if npy is not None:
        import numpy as np

        np.save(npy, result.data)
        written.append(str(npy))
    if png is None:
        return written
    from sogm_service.apps.render import save_grid_png

    p = result.probabilities()
    if p.ndim == 2:
        title = f"fused ({result.method}) over {', '.join(result.layers)}"
        save_grid_png(png, p, result.geometry, title=title)
        written.append(str(png))
        return written
    for k, layer in enumerate(result.layers):
        path = png if len(result.layers) == 1 else png.with_name(
            f"{png.stem}_{layer.replace('/', '_')}{png.suffix}")
        save_grid_png(path, p[k], result.geometry, title=f"layer {layer}")
        written.append(str(path))
    return written


def _publish_ism(args: argparse.Namespace) -> int:
    import numpy as np

    from sogm_service.client.mapclient import build_ism
    from sogm_service.core.geometry import Pose2D

    data = _read_grid(args.file)
    yaw = _yaw(args)
    origin = Pose2D(args.x, args.y, yaw)
    # Checked before connecting: a bad file never waits for a network.
    build_ism(data, resolution=args.resolution, origin=origin, encoding=args.encoding,
              layer=args.layer, frame=args.frame)
    with _client(args) as client:
        msg = client.publish_ism(args.key, data, resolution=args.resolution, origin=origin,
                                 encoding=args.encoding, layer=args.layer, frame=args.frame,
                                 wait=not args.no_wait, timeout=args.wait_timeout)
    state = "published" if args.no_wait else "fused"
    print(f"{state} {msg.width}x{msg.height} {msg.encoding} ISM on {args.key} "
          f"({np.asarray(data).nbytes} bytes)")
    return 0


def _read_grid(path: Path) -> Any:
    import cv2
    import numpy as np

    if not path.is_file():
        raise _usage(f"{path}: no such file")
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise _usage(f"{path} is not a readable .npy array: {_one_line(exc)}") from None
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise _usage(f"cannot read {path} as an image (or use a .npy)")
    # Image convention: dark = occupied, row 0 at the top; map rows grow upward.
    return np.ascontiguousarray((255 - img)[::-1])


def _schemas(args: argparse.Namespace) -> int:
    from sogm_service.wire import codec

    if args.check:
        stale = codec.stale_schemas(args.out)
        if stale:
            print(f"stale schemas in {args.out}: {stale}; run sogm-service schemas",
                  file=sys.stderr)
            return 1
        print(f"schemas in {args.out} are up to date")
        return 0
    for path in codec.write_schemas(args.out):
        print(f"wrote {path}")
    return 0


def _router(args: argparse.Namespace) -> int:
    from sogm_service.client.session import check_endpoint, open_session
    from sogm_service.service.config import ZenohSettings

    for endpoint in args.listen or []:
        why = check_endpoint(endpoint)
        if why is not None:
            return _fail("router", why)
    if args.config is not None:  # the file as it is; --listen only when given
        if not args.config.is_file():
            return _fail("router", f"--config {args.config}: no such file")
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
