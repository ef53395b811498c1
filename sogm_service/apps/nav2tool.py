"""sogm-service export nav2 and sogm-service import nav2: maps for and from nav2.

export nav2 --out DIR writes map.yaml + map.pgm exactly as nav2's map_server reads them
(trinary) from a running server's fused map (Eq. 6 over the chosen layers, max by default).
import nav2 map.yaml --layer NAME fuses such a map into a running server as a prior ISM (in
blocks small enough for the server's ISM limits).  Both talk to the server as any client does,
and both need the ros2 extra (pyyaml), imported only when the command runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from sogm_service.apps.options import PROG, command, fail, require_extra, subcommands


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
                   help="comma-separated layers (default: all)")
    p.add_argument("--method", choices=["max", "bayes"], default="max",
                   help="Eq. 6 pooling of the layers: max (a cell is occupied when a layer "
                        "that observed it says so, free when those say free, unknown when "
                        "none did) or bayes (the sum of their log-odds)")
    p.add_argument("--box", type=float, nargs=4, default=None,
                   metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="the region in metres (default: every tile of the map)")
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

    with MapClient.connect(args.connect, map_name=args.map, timeout=args.timeout,
                           zenoh_config=args.zenoh_config) as client:
        box = args.box or client.info().bounds
        if box is None:
            return fail("export nav2", "the map is empty")
        xmin, ymin, xmax, ymax = box
        layers = args.layers.split(",") if args.layers else None
        fused = client.fused(method=args.method, x=(xmin + xmax) / 2, y=(ymin + ymax) / 2,
                             width=xmax - xmin, height=ymax - ymin, layers=layers,
                             interp="nearest", encoding="logodds_i16")
    yml, pgm = write_nav2(args.out, fused.data, fused.geometry, kind="fixed", name=args.name)
    counts = trinary_counts(trinary_pixels(fused.data, "fixed"))
    print(f"wrote {yml} and {pgm} ({fused.geometry.width}x{fused.geometry.height} cells at "
          f"{fused.geometry.resolution} m: {counts})")
    if counts.free == 0:
        print(f"{PROG}: export nav2: warning: the map has no free cell, so nav2 can plan "
              "through none (no layer chosen observed free space here)", file=sys.stderr)
    return 0


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

