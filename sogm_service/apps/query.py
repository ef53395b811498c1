"""sogm-service query submap|fused|supercells|info|stats: ask a running server.

A query nobody answers is explained from what the client can see: the servers' liveliness
tokens (prefix/map/@server/*) say whether any server holds the map, and which maps the
servers that are there do hold.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

from sogm_service.apps.options import (
    UsageError,
    angle_options,
    command,
    connection_args,
    subcommands,
    yaw,
)
from sogm_service.core.sevds.segment import SevdsParams

_SEVDS = SevdsParams()  # the supercells query's defaults

EPILOG = """examples:
  sogm-service query submap --x 2 --y 1 --yaw-deg 30 --width 6 --height 4 --png sub.png
  sogm-service query fused --method max --width 20 --height 20 --json
  sogm-service query submap --layers '*/laser/obstacle' --width 20 --height 20 --json
  sogm-service query supercells --x 2 --y 2 --width 6.4 --height 6.4 --png graph.png
  sogm-service query info
"""
GRIDS = {"submap": "the chosen layers resampled into a window (any pose and resolution)",
         "fused": "Eq. 6 over the chosen layers: bayes (P_B) or max (P_M)",
         "supercells": "the SEVDS topometric graph of a window (paper III-D.2)"}
REPORTS = {"info": "the map: frame, resolution, layers, tiles, bounds",
           "stats": "counters, rejections per reason, queue, latencies"}


def add_parser(subparsers: Any) -> None:
    query = command(subparsers, "query", "query a running server", epilog=EPILOG)
    sub = subcommands(query, "what", "WHAT")
    for name, text in GRIDS.items():
        q = command(sub, name, text, epilog=EPILOG)
        connection_args(q)
        _window_args(q)
        _output_args(q)
        if name == "fused":
            q.add_argument("--method", default="bayes", choices=["bayes", "max"],
                           help="bayes: super-Bayesian sum of log-odds (P_B); max: the most "
                                "occupied layer per cell (P_M)")
        if name == "supercells":
            _sevds_args(q)
        q.set_defaults(handler=run)
    for name, text in REPORTS.items():
        q = command(sub, name, text)
        connection_args(q)
        q.add_argument("--json", action="store_true",
                       help="print JSON (what info and stats always print; accepted for "
                            "symmetry)")
        q.set_defaults(handler=run)


def _window_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("window (map frame)")
    g.add_argument("--x", type=float, default=0.0, metavar="M", help="window centre x (m)")
    g.add_argument("--y", type=float, default=0.0, metavar="M", help="window centre y (m)")
    angle_options(g, "window")
    g.add_argument("--width", type=float, default=10.0, metavar="M", help="window width (m)")
    g.add_argument("--height", type=float, default=10.0, metavar="M",
                   help="window height (m)")
    g.add_argument("--resolution", type=float, default=None, metavar="M",
                   help="cell size of the answer (m; default: the map's)")
    g.add_argument("--layers", default=None, metavar="A,B",
                   help="comma-separated layers (default: all); a glob pattern names a class, "
                        "its layers fused (Bayes) into one named by the pattern: "
                        "'*/laser/obstacle' is every robot's (quote it in a shell)")
    g.add_argument("--interp", default="biodds", choices=["biodds", "bilinear", "nearest"],
                   help="resampling: biodds (the paper's Eq. 3-5: bilinear in log-odds), "
                        "bilinear (in probability), nearest")


def _output_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("output")
    g.add_argument("--json", action="store_true",
                   help="print the result as one JSON object (for scripts) instead of text")
    g.add_argument("--png", type=Path, default=None, metavar="FILE",
                   help="write a picture (legend, scale bar in m, map axes; at least 512 px); "
                        "several layers: one FILE_<layer>.png each (default: none)")
    g.add_argument("--npy", type=Path, default=None, metavar="FILE",
                   help="write the array (layers, rows, cols) in the reply's encoding "
                        "(default: none)")
    g.add_argument("--encoding", default="prob_f32",
                   choices=["prob_u8", "prob_f32", "logodds_i16", "occupancy_i8", "prob_u8_v2"],
                   help="cell encoding of the reply (and of --npy): probabilities as float32 "
                        "or 0..255, log-odds in 1/1000 nat, nav_msgs 0..100/-1, or prob_u8_v2 "
                        "(255 = unknown)")


def _sevds_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("SEVDS parameters (paper Eq. 7-10)")
    g.add_argument("--block-size", type=int, default=_SEVDS.block_size, metavar="CELLS",
                   help="edge of the initial square supercells (cells)")
    g.add_argument("--levels", type=int, default=_SEVDS.levels, metavar="N",
                   help="block levels (each halves the block) before cell moves")
    g.add_argument("--bins", type=int, default=_SEVDS.bins, metavar="N",
                   help="histogram bins per layer (probability quantisation)")
    g.add_argument("--iterations", type=int, default=_SEVDS.iterations, metavar="N",
                   help="cell-level sweeps")
    g.add_argument("--gamma", type=float, default=_SEVDS.gamma,
                   help="weight of the boundary term, unitless (smoother borders when larger)")
    g.add_argument("--criterion", default=_SEVDS.criterion, choices=["distribution", "energy"],
                   help="energy (the default): a move must lower the total squared deviation "
                        "(+ gamma x perimeter) of both supercells; distribution: the paper's "
                        "rule, the receiver's summed histogram variance")


def open_client(args: argparse.Namespace) -> Any:
    """The MapClient of a client command's connection options."""
    from sogm_service.client.mapclient import DEFAULT_TIMEOUT_S, MapClient

    if args.zenoh_config is not None and not args.zenoh_config.is_file():
        raise UsageError(f"--zenoh-config {args.zenoh_config}: no such file")
    client = MapClient.connect(args.connect, map_name=args.map, prefix=args.prefix,
                               timeout=args.timeout or DEFAULT_TIMEOUT_S,
                               zenoh_config=args.zenoh_config)
    if args.timeout:
        client.supercells_timeout = args.timeout
    client.compression = None if args.compression == "none" else "zstd"
    return client


def run(args: argparse.Namespace) -> int:
    from sogm_service.wire.errors import QueryTimeoutError

    # A bad --yaw is refused before anything is asked (or connected to).
    window = _window(args) if args.what in GRIDS else {}
    with open_client(args) as client:
        started = time.monotonic()
        try:
            return _run_query(client, args, window)
        except QueryTimeoutError as exc:
            raise unanswered(client, args, exc, time.monotonic() - started) from None


def unanswered(client: Any, args: argparse.Namespace, exc: Exception,
               elapsed: float) -> UsageError:
    """What a query nobody answered tells: no server of the map, or a server that is there
    and did not answer in time."""
    servers = client.servers(timeout=1.0)
    if servers:
        return UsageError(f"{exc} (after {elapsed:.2f} s; server(s) {', '.join(servers)} of "
                          f"map {args.map!r} are alive)")
    where = args.zenoh_config or args.connect
    text = (f"no server answers for map {args.map!r} at {where}: none holds a "
            f"{args.prefix}/{args.map}/@server/* liveliness token")
    maps = served_maps(client, args.prefix)
    return UsageError(text + (f"; maps served there: {', '.join(maps)}" if maps else ""))


def served_maps(client: Any, prefix: str) -> list[str]:
    """The maps whose servers' liveliness tokens the client sees under ``prefix``."""
    key = f"{prefix.strip('/')}/*/@server/*"
    replies = client.session.liveliness().get(key, timeout=1.0)
    keys = [str(r.ok.key_expr) for r in replies if r.ok is not None]
    return sorted({k.split("/")[-3] for k in keys})


def _window(args: argparse.Namespace) -> dict[str, Any]:
    layers = args.layers.split(",") if args.layers else None
    return dict(x=args.x, y=args.y, yaw=yaw(args), width=args.width, height=args.height,
                resolution=args.resolution, layers=layers, interp=args.interp)


def _run_query(client: Any, args: argparse.Namespace, window: dict[str, Any]) -> int:
    if args.what in REPORTS:
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
            "classes": reply.classes or {},
            "origin": reply.origin.model_dump(), "written": written}))
        return 0
    print(f"supercells: {len(reply.nodes)} nodes, {edges} edges over {reply.width}x"
          f"{reply.height} cells at {reply.resolution} m, layers {reply.layers}"
          f"{_classes_text(reply.classes or {})}")
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
            "layers": list(result.layers), "classes": result.classes,
            "encoding": result.encoding,
            "known_fraction": round(known, 6), "occupied_fraction": round(occupied, 6),
            "stamp": result.stamp, "written": written}))
        return
    print(f"{'fused (' + result.method + ')' if result.method else 'submap'}: "
          f"{g.width}x{g.height} cells at {g.resolution} m, origin ({g.origin.x:.3f}, "
          f"{g.origin.y:.3f}, {math.degrees(g.origin.yaw):.1f} deg), layers {result.layers}"
          f"{_classes_text(result.classes)}")
    print(f"known cells: {known * 100:.1f} %, occupied (p > 0.5): {occupied * 100:.1f} %")
    if known == 0.0:
        print("note: no cell of this window has been observed (is it inside the map? "
              "'sogm-service query info' gives the bounds)", file=sys.stderr)
    for path in written:
        print(f"wrote {path}")


def file_part(layer: str) -> str:
    """A layer's name or pattern as part of a file name: ``*/laser/obstacle`` ->
    ``all_laser_obstacle``, ``robot?/x`` -> ``robot-_x`` (no glob or path characters)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", layer.replace("*", "all").replace("?", "-"))


def _classes_text(classes: dict[str, list[str]]) -> str:
    return "".join(f"\n  class {name}: {' + '.join(members)}"
                   for name, members in classes.items())


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
            f"{png.stem}_{file_part(layer)}{png.suffix}")
        save_grid_png(path, p[k], result.geometry, title=f"layer {layer}")
        written.append(str(path))
    return written
