"""sogm-service export nav2 and sogm-service import nav2: maps for and from nav2.

export nav2 --out DIR writes map.yaml + map.pgm exactly as nav2's map_server reads them
(trinary) from a running server's fused map (Eq. 6 over the chosen layers, max by default);
with --keepout and --speed also nav2's costmap filter masks (keepout_mask, speed_mask: the
rules of the live ROS 2 masks, in sogm_service.adapters.ros2.filters).
import nav2 map.yaml --layer NAME fuses such a map into a running server as a prior ISM (in
blocks small enough for the server's ISM limits).  Both talk to the server as any client does,
and both need the ros2 extra (pyyaml), imported only when the command runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from sogm_service.apps.options import PROG, command, fail, require_extra, subcommands

if TYPE_CHECKING:
    from sogm_service.adapters.ros2.filters import FilterSpec
    from sogm_service.client import MapClient


def _connection(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                   help="Zenoh endpoint of the server or a router")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config, honoured as is; replaces --connect "
                        "(default: none)")
    p.add_argument("--map", default="default", help="map name")
    p.add_argument("--timeout", type=float, default=30.0, metavar="S",
                   help="query timeout (s)")


def add_parser(subparsers: Any) -> None:
    ex = command(subparsers, "export", "export nav2 --out DIR: map.yaml + map.pgm for nav2's "
                                       "map_server", description=__doc__ or "")
    p = command(subcommands(ex, "format", "FORMAT"), "nav2",
                "write map.yaml + map.pgm as nav2's map_server reads them (needs the ros2 "
                "extra)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="directory for the two files")
    p.add_argument("--name", default="map", help="file stem")
    p.add_argument("--layers", default=None, metavar="A,B",
                   help="comma-separated layers or class patterns, e.g. '*/laser/obstacle' "
                        "(a pattern's layers fused by the Bayesian rule; default: all)")
    p.add_argument("--method", choices=["max", "bayes"], default="max",
                   help="Eq. 6 pooling of the layers: max (a cell is occupied when a layer "
                        "that observed it says so, free when those say free, unknown when "
                        "none did) or bayes (the sum of their log-odds)")
    p.add_argument("--box", type=float, nargs=4, default=None,
                   metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="the region in metres (default: every tile of the map)")
    p.add_argument("--keepout", default=None, metavar="A,B",
                   help="also write keepout_mask.yaml + .pgm (trinary) for nav2's "
                        "KeepoutFilter: 100 where one of these layers or class patterns is at "
                        "or above --keepout-threshold, 0 where they observed less, -1 where "
                        "none observed the cell")
    p.add_argument("--keepout-threshold", type=float, default=0.6, metavar="P",
                   help="probability at or above which a cell is kept out (default 0.6)")
    p.add_argument("--speed", default=None, metavar="PATTERN=PERCENT,...",
                   help="also write speed_mask.yaml + .pgm (scale) for nav2's SpeedFilter "
                        "(percent, base 0, multiplier 1): each layer or class pattern's limit "
                        "(1..100) where it is at or above --speed-threshold, the lowest where "
                        "several are, 0 (no limit) elsewhere")
    p.add_argument("--speed-threshold", type=float, default=0.6, metavar="P",
                   help="probability at or above which a speed class limits a cell "
                        "(default 0.6)")
    _connection(p)
    p.set_defaults(handler=export_nav2)
    im = command(subparsers, "import", "import nav2 map.yaml --layer NAME: fuse a nav2 map as "
                                       "a prior", description=__doc__ or "")
    p = command(subcommands(im, "format", "FORMAT"), "nav2",
                "fuse a nav2 map (map.yaml + image) as a prior ISM (needs the ros2 extra)")
    p.add_argument("yaml", type=Path, help="the map's YAML file")
    p.add_argument("--layer", required=True, help="the layer to fuse it into")
    p.add_argument("--max-side", type=int, default=1024, metavar="CELLS",
                   help="ISMs of at most this many cells a side")
    _connection(p)
    p.set_defaults(handler=import_nav2)


def export_main(argv: list[str]) -> int:
    """sogm-service export with these arguments."""
    from sogm_service.apps import cli

    return cli.main(["export", *argv])


def import_main(argv: list[str]) -> int:
    """sogm-service import with these arguments."""
    from sogm_service.apps import cli

    return cli.main(["import", *argv])


def export_nav2(args: argparse.Namespace) -> int:
    require_extra("ros2", "export nav2")
    from sogm_service.adapters.nav2 import export_nav2 as write_nav2
    from sogm_service.adapters.nav2 import trinary_counts, trinary_pixels
    from sogm_service.client import MapClient

    try:
        spec = _filter_spec(args)
    except ValueError as exc:
        return fail("export nav2", str(exc))
    with MapClient.connect(args.connect, map_name=args.map, timeout=args.timeout,
                           zenoh_config=args.zenoh_config) as client:
        info = client.info()
        box = args.box or info.bounds
        if box is None:
            return fail("export nav2", "the map is empty")
        xmin, ymin, xmax, ymax = box
        layers = args.layers.split(",") if args.layers else None
        window: dict[str, Any] = dict(x=(xmin + xmax) / 2, y=(ymin + ymax) / 2, width=xmax - xmin,
                                      height=ymax - ymin, interp="nearest",
                                      encoding="logodds_i16")
        fused = client.fused(method=args.method, layers=layers, **window)
        masks = _masks(client, spec, info.layers, window, fused.data.shape) \
            if spec.enabled else {}
    yml, pgm = write_nav2(args.out, fused.data, fused.geometry, kind="fixed", name=args.name)
    from sogm_service.adapters.nav2 import MASK_MODES, export_mask

    for mask, cells in masks.items():
        my, mp = export_mask(args.out, cells, fused.geometry, mode=MASK_MODES[mask],
                             name=f"{mask}_mask")
        values, n_cells = np.unique(cells, return_counts=True)
        print(f"wrote {my} and {mp} ({MASK_MODES[mask]}: "
              + ", ".join(f"{n} cells {v}" for v, n in zip(values, n_cells, strict=True)) + ")")
    counts = trinary_counts(trinary_pixels(fused.data, "fixed"))
    print(f"wrote {yml} and {pgm} ({fused.geometry.width}x{fused.geometry.height} cells at "
          f"{fused.geometry.resolution} m: {counts})")
    if counts.free == 0:
        print(f"{PROG}: export nav2: warning: the map has no free cell, so nav2 can plan "
              "through none (no layer chosen observed free space here)", file=sys.stderr)
    return 0


def _filter_spec(args: argparse.Namespace) -> FilterSpec:
    """The masks asked by --keepout and --speed (ValueError for a malformed one)."""
    from sogm_service.adapters.ros2.filters import spec_from_options

    return spec_from_options(args.keepout, args.keepout_threshold, args.speed,
                             args.speed_threshold)


def _masks(client: MapClient, spec: FilterSpec, names: list[str], window: dict[str, Any],
           shape: tuple[int, ...]) -> dict[str, npt.NDArray[np.int8]]:
    """The masks of ``spec`` over ``window``: each class read once as the server fuses it
    (entries matching no layer are left out, as the live masks leave them)."""
    from sogm_service.adapters.ros2.filters import (
        KEEPOUT,
        SPEED,
        filter_classes,
        keepout_cells,
        speed_cells,
    )

    classes = filter_classes(spec, names)
    wanted = [c.name for c in [*classes.keepout, *classes.speed]]
    read = list(dict.fromkeys(wanted))
    planes: dict[str, npt.NDArray[np.int16]] = {}
    if read:
        sub = client.submap(layers=read, **window)
        planes = {n: sub.data[k] for k, n in enumerate(read)}

    def stack(cls: list[str]) -> npt.NDArray[np.int16]:
        return np.stack([planes[n] for n in cls]) if cls else np.zeros((0, *shape), np.int16)

    out: dict[str, npt.NDArray[np.int8]] = {}
    if spec.keepout:
        out[KEEPOUT] = keepout_cells(stack([c.name for c in classes.keepout]),
                                     spec.keepout_threshold)
    if spec.speed:
        out[SPEED] = speed_cells(stack([c.name for c in classes.speed]), classes.limits,
                                 spec.speed_threshold)
    return out


def import_nav2(args: argparse.Namespace) -> int:
    require_extra("ros2", "import nav2")
    from sogm_service.adapters.nav2 import Nav2MapError, read_nav2
    from sogm_service.client import MapClient
    from sogm_service.wire import codec

    try:
        nav2 = read_nav2(args.yaml)
        with MapClient.connect(args.connect, map_name=args.map, timeout=args.timeout,
                               zenoh_config=args.zenoh_config) as client:
            frame = client.info().frame
            chunks = nav2.ism_chunks(args.max_side, layer=args.layer, frame=frame)
            for ism in chunks:  # the layer field names the layer whatever the key
                client.publish_raw(f"ism/{args.layer}", codec.encode(ism))
    except Nav2MapError as exc:
        return fail("import nav2", f"{args.yaml}: [{exc.code}] {exc}")
    g = nav2.geometry
    print(f"published {len(chunks)} ISM(s) of layer {args.layer!r}: {g.width}x{g.height} cells "
          f"at {g.resolution} m")
    return 0

