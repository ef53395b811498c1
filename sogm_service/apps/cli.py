"""The ``sogm-service`` command.

Heavy modules (zenoh, numba kernels, the simulator) are imported only by the subcommand that
needs them, so ``serve`` starts fast.  Subcommands owned by other modules (``tiles``, ``eval``)
get the rest of the command line and build their own parser.
"""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sogm_service.service.session import DEFAULT_ENDPOINT


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

    return bench.main(argv)


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


def _window_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--x", type=float, default=0.0, help="window centre x (m)")
    p.add_argument("--y", type=float, default=0.0, help="window centre y (m)")
    p.add_argument("--yaw", type=float, default=0.0, help="window heading (rad)")
    p.add_argument("--width", type=float, default=10.0, help="window width (m)")
    p.add_argument("--height", type=float, default=10.0, help="window height (m)")
    p.add_argument("--resolution", type=float, default=None, help="cell size (m); map's")
    p.add_argument("--layers", default=None, help="comma-separated layers (default all)")
    p.add_argument("--interp", default="biodds", choices=["biodds", "bilinear", "nearest"])


def _connection_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", default="tcp/127.0.0.1:7447",
                   help="Zenoh endpoint of the server or a router (default %(default)s)")
    p.add_argument("--map", default="default", help="map name (default %(default)s)")
    p.add_argument("--prefix", default="sogm", help="key prefix (default %(default)s)")
    p.add_argument("--timeout", type=float, default=5.0, help="query timeout (s)")
    _zenoh_config_arg(p)


def _zenoh_config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config, honoured as is (mode, TLS, endpoints), e.g. one "
                        "written by 'sogm-service certs'; replaces --connect")


DEFAULT_ROUTER_LISTEN = "tcp/127.0.0.1:7447"
DEFAULT_SERVE_LISTEN = DEFAULT_ENDPOINT  # where every client command connects by default


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sogm-service", description="Semantical occupancy grid map server on Zenoh.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="run the map server daemon")
    serve.add_argument("--config", type=Path, default=None, help="TOML config file")
    serve.add_argument("--listen", action="append", default=None,
                       help="Zenoh listen endpoint (repeatable; overrides the config; default "
                            f"{DEFAULT_SERVE_LISTEN} when the config names no endpoint)")
    serve.add_argument("--connect", action="append", default=None,
                       help="Zenoh connect endpoint (repeatable; overrides the config)")
    serve.add_argument("--storage", type=Path, default=None, help="tile store directory")
    _zenoh_config_arg(serve)
    serve.add_argument("--ros2", action="store_true",
                       help="serve ROS 2 robots and tools over rmw_zenoh ([ros2] enabled; "
                            "needs the ros2 extra)")
    serve.add_argument("--ros2-domain", type=int, default=None, metavar="N",
                       help="ROS_DOMAIN_ID (default: the config's, 0)")

    query = sub.add_parser("query", help="query a running server")
    qsub = query.add_subparsers(dest="what", required=True)
    for name in ("submap", "fused", "supercells"):
        q = qsub.add_parser(name, help=f"the {name} queryable")
        _connection_args(q)
        _window_args(q)
        q.add_argument("--png", type=Path, default=None, help="write a picture here")
        q.add_argument("--npy", type=Path, default=None, help="write the array here")
        if name == "fused":
            q.add_argument("--method", default="bayes", choices=["bayes", "max"])
        if name == "supercells":
            q.add_argument("--block-size", type=int, default=8)
            q.add_argument("--levels", type=int, default=3)
            q.add_argument("--bins", type=int, default=5)
            q.add_argument("--iterations", type=int, default=4)
            q.add_argument("--gamma", type=float, default=0.01)
            q.add_argument("--criterion", default="distribution",
                           choices=["distribution", "energy"])
    for name in ("info", "stats"):
        _connection_args(qsub.add_parser(name, help=f"the {name} queryable"))

    pub = sub.add_parser("publish-ism", help="send an ISM from a .npy or image file")
    _connection_args(pub)
    pub.add_argument("file", type=Path, help=".npy (uint8/int8/float32) or an image (grey)")
    pub.add_argument("--key", default="ism/cli/manual", help="key (default %(default)s)")
    pub.add_argument("--resolution", type=float, required=True, help="ISM cell size (m)")
    pub.add_argument("--x", type=float, default=0.0, help="origin x of cell (0,0) corner")
    pub.add_argument("--y", type=float, default=0.0, help="origin y of cell (0,0) corner")
    pub.add_argument("--yaw", type=float, default=0.0, help="origin heading (rad)")
    pub.add_argument("--encoding", default=None,
                     choices=["prob_u8", "occupancy_i8", "prob_f32", "prob_u8_v2"])
    pub.add_argument("--layer", default=None, help="layer name (default: key remainder)")
    pub.add_argument("--frame", default="map")

    schemas = sub.add_parser("schemas", help="write the JSON Schema of every message")
    schemas.add_argument("--out", type=Path, default=Path("schemas"))
    schemas.add_argument("--check", action="store_true", help="fail if files are stale")

    router = sub.add_parser("router", help="run a Zenoh router (Python) for robots and servers")
    router.add_argument("--listen", action="append", default=None,
                        help=f"endpoint (repeatable; default {DEFAULT_ROUTER_LISTEN}: loopback "
                             "only, name the site address to open it)")
    router.add_argument("--config", "--zenoh-config", dest="config", type=Path, default=None,
                        metavar="FILE", help="Zenoh JSON5 config, honoured as is (its mode "
                                             "and listeners too)")

    for name, (_, text) in _DELEGATED.items():
        d = sub.add_parser(name, help=text, add_help=False)
        d.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


# Processes that fuse or sample for long: their large temporaries are kept on the heap
# (:mod:`sogm_service.service.allocator`), which the short-lived commands do not need.
_LONG_RUNNING = frozenset({"serve", "demo", "replay", "bench"})


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in _LONG_RUNNING:
        from sogm_service.service.allocator import keep_large_allocations

        keep_large_allocations()
    parser = build_parser()
    # Delegated subcommands parse their own options (including -h).
    if argv and argv[0] in _DELEGATED:
        _setup_logging(False)
        return _DELEGATED[argv[0]][0](argv[1:])
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    if args.command in _DELEGATED:  # after a global option such as -v
        return _DELEGATED[args.command][0](args.rest)
    handler = {"serve": _serve, "query": _query, "publish-ism": _publish_ism,
               "schemas": _schemas, "router": _router}[args.command]
    return handler(args)


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


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


def _serve(args: argparse.Namespace) -> int:
    from sogm_service.service.config import ConfigError, load_config

    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"sogm-service serve: {exc}", file=sys.stderr)
        return 2
    updates: dict[str, Any] = {}
    if args.listen:
        updates["listen"] = args.listen
    if args.connect:
        updates["connect"] = args.connect
    if args.zenoh_config:
        updates["config_file"] = args.zenoh_config
    z = config.zenoh
    if not (updates or z.listen or z.connect or z.config_file):  # meet the clients' default
        updates["listen"] = [DEFAULT_SERVE_LISTEN]
    if updates:
        config = config.model_copy(update={"zenoh": config.zenoh.model_copy(update=updates)})
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
            print(f"sogm-service serve: --ros2-domain: {exc.errors()[0]['msg']}",
                  file=sys.stderr)
            return 2
        config = config.model_copy(update={"ros2": section})
    from sogm_service.service.server import MapServer
    from sogm_service.wire.errors import StoreLockedError

    stop = stop_on_signal()
    try:
        server = MapServer(config).start()
    except StoreLockedError as exc:  # an operator's mistake: one line, no traceback
        print(f"sogm-service serve: store {exc.directory} is locked by "
              f"{'pid ' + str(exc.pid) if exc.pid is not None else 'another process'}; "
              "one server per store directory", file=sys.stderr)
        return 2
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
    from sogm_service.service.client import MapClient

    return MapClient.connect(args.connect, map_name=args.map, prefix=args.prefix,
                             timeout=args.timeout, zenoh_config=args.zenoh_config)


def _query(args: argparse.Namespace) -> int:
    from sogm_service.wire.errors import ClientError

    with _client(args) as client:
        try:
            return _run_query(client, args)
        except ClientError as exc:
            print(f"sogm-service query {args.what}: {exc}", file=sys.stderr)
            return 1


def _window(args: argparse.Namespace) -> dict[str, Any]:
    layers = args.layers.split(",") if args.layers else None
    return dict(x=args.x, y=args.y, yaw=args.yaw, width=args.width, height=args.height,
                resolution=args.resolution, layers=layers, interp=args.interp)


def _run_query(client: Any, args: argparse.Namespace) -> int:
    if args.what in ("info", "stats"):
        reply = client.info() if args.what == "info" else client.stats()
        print(reply.model_dump_json(indent=2))
        return 0
    if args.what == "supercells":
        return _run_supercells(client, args)
    if args.what == "submap":
        result = client.submap(**_window(args))
    else:
        result = client.fused(method=args.method, **_window(args))
    _print_grid(result)
    _write_grid_outputs(result, args.png, args.npy)
    return 0


def _run_supercells(client: Any, args: argparse.Namespace) -> int:
    window = _window(args)
    reply = client.supercells(**window, block_size=args.block_size, levels=args.levels,
                              bins=args.bins, iterations=args.iterations, gamma=args.gamma,
                              criterion=args.criterion, labels=args.png is not None)
    edges = sum(len(n.neighbors) for n in reply.nodes) // 2
    print(f"supercells: {len(reply.nodes)} nodes, {edges} edges over {reply.width}x"
          f"{reply.height} cells at {reply.resolution} m, layers {reply.layers}")
    for node in reply.nodes[:5]:
        print(f"  #{node.id}: ({node.x:.2f}, {node.y:.2f}) m, {node.area_m2:.2f} m2, "
              f"mean P {[round(p, 2) for p in node.mean_probability]}")
    if args.npy is not None:
        import numpy as np

        np.save(args.npy, np.array([[n.x, n.y, *n.mean_probability] for n in reply.nodes]))
    if args.png is not None:
        import cv2

        window.pop("layers", None)
        fused = client.fused(method="max", **window, layers=reply.layers, encoding="prob_f32")
        from sogm_service.apps.render import draw_graph

        cv2.imwrite(str(args.png), draw_graph(reply, fused))
        print(f"wrote {args.png}")
    return 0


def _print_grid(result: Any) -> None:
    g = result.geometry
    p = result.probabilities()
    known = abs(p - 0.5) > 1e-3
    print(f"{'fused (' + result.method + ')' if result.method else 'submap'}: "
          f"{g.width}x{g.height} cells at {g.resolution} m, origin ({g.origin.x:.3f}, "
          f"{g.origin.y:.3f}, {g.origin.yaw:.3f} rad), layers {result.layers}")
    print(f"known cells: {known.mean() * 100:.1f} %, occupied (p > 0.5): "
          f"{(p > 0.5 + 1e-3).mean() * 100:.1f} %")


def _write_grid_outputs(result: Any, png: Path | None, npy: Path | None) -> None:
    import cv2
    import numpy as np

    from sogm_service.apps.render import probability_image

    if npy is not None:
        np.save(npy, result.data)
        print(f"wrote {npy}")
    if png is None:
        return
    p = result.probabilities()
    if p.ndim == 2:
        cv2.imwrite(str(png), probability_image(p))
        print(f"wrote {png}")
        return
    for k, layer in enumerate(result.layers):
        path = png if len(result.layers) == 1 else png.with_name(
            f"{png.stem}_{layer.replace('/', '_')}{png.suffix}")
        cv2.imwrite(str(path), probability_image(p[k]))
        print(f"wrote {path}")


def _publish_ism(args: argparse.Namespace) -> int:
    import numpy as np

    from sogm_service.core.geometry import Pose2D

    data = _read_grid(args.file)
    with _client(args) as client:
        msg = client.publish_ism(args.key, data, resolution=args.resolution,
                                 origin=Pose2D(args.x, args.y, args.yaw),
                                 encoding=args.encoding, layer=args.layer, frame=args.frame)
    print(f"published {msg.width}x{msg.height} {msg.encoding} ISM on {args.key} "
          f"({np.asarray(data).nbytes} bytes)")
    return 0


def _read_grid(path: Path) -> Any:
    import cv2
    import numpy as np

    if path.suffix == ".npy":
        return np.load(path, allow_pickle=False)
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise SystemExit(f"cannot read {path} as an image")
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
    from sogm_service.service.config import ZenohSettings
    from sogm_service.service.session import open_session

    if args.config is not None:  # the file as it is; --listen only when given
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
