"""``sogm-service export nav2`` and ``sogm-service import nav2``: maps for and from nav2.

``export nav2 --out DIR`` writes ``map.yaml`` + ``map.pgm`` exactly as nav2's map_server reads
them (trinary; :func:`sogm_service.adapters.nav2.export_nav2`) from a running server's fused
map (Eq. 6 over the chosen layers, ``max`` by default).  ``import nav2 map.yaml --layer NAME``
fuses such a map into a running server as a prior ISM (in blocks small enough for the server's
ISM limits).  Both talk to the server as any client does.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sogm_service.adapters.nav2 import Nav2MapError, export_nav2, read_nav2
from sogm_service.client import ClientError, MapClient
from sogm_service.wire import codec


def _connection(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", default="tcp/127.0.0.1:7447",
                   help="Zenoh endpoint of the server or a router (default %(default)s)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config, honoured as is (replaces --connect)")
    p.add_argument("--map", default="default", help="map name (default %(default)s)")
    p.add_argument("--timeout", type=float, default=30.0, help="query timeout, s")


def export_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sogm-service export nav2",
                                description="write map.yaml + map.pgm as nav2's map_server "
                                            "reads them")
    p.add_argument("--out", type=Path, required=True, help="directory for the two files")
    p.add_argument("--name", default="map", help="file stem (default %(default)s)")
    p.add_argument("--layers", default=None, help="comma-separated layers (default all)")
    p.add_argument("--method", choices=["max", "bayes"], default="max",
                   help="Eq. 6 pooling of the layers (default %(default)s)")
    p.add_argument("--box", type=float, nargs=4, default=None,
                   metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                   help="the region in metres (default: every tile of the map)")
    _connection(p)
    return p


def import_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sogm-service import nav2",
                                description="fuse a nav2 map (map.yaml + image) as a prior ISM")
    p.add_argument("yaml", type=Path, help="the map's YAML file")
    p.add_argument("--layer", required=True, help="the layer to fuse it into")
    p.add_argument("--max-side", type=int, default=1024,
                   help="ISMs of at most this many cells a side (default %(default)s)")
    _connection(p)
    return p


def export_main(argv: list[str]) -> int:
    if argv[:1] != ["nav2"]:
        print("sogm-service export: the one format is nav2 (export nav2 --out DIR)",
              file=sys.stderr)
        return 2
    args = export_parser().parse_args(argv[1:])
    try:
        with MapClient.connect(args.connect, map_name=args.map, timeout=args.timeout,
                               zenoh_config=args.zenoh_config) as client:
            box = args.box or client.info().bounds
            if box is None:
                print("sogm-service export nav2: the map is empty", file=sys.stderr)
                return 2
            xmin, ymin, xmax, ymax = box
            layers = args.layers.split(",") if args.layers else None
            fused = client.fused(method=args.method, x=(xmin + xmax) / 2, y=(ymin + ymax) / 2,
                                 width=xmax - xmin, height=ymax - ymin, layers=layers,
                                 interp="nearest", encoding="logodds_i16")
    except ClientError as exc:
        print(f"sogm-service export nav2: {exc}", file=sys.stderr)
        return 2
    yml, pgm = export_nav2(args.out, fused.data, fused.geometry, kind="fixed", name=args.name)
    print(f"wrote {yml} and {pgm} ({fused.geometry.width}x{fused.geometry.height} cells at "
          f"{fused.geometry.resolution} m)")
    return 0


def import_main(argv: list[str]) -> int:
    if argv[:1] != ["nav2"]:
        print("sogm-service import: the one format is nav2 (import nav2 map.yaml --layer NAME)",
              file=sys.stderr)
        return 2
    args = import_parser().parse_args(argv[1:])
    try:
        nav2 = read_nav2(args.yaml)
        with MapClient.connect(args.connect, map_name=args.map, timeout=args.timeout,
                               zenoh_config=args.zenoh_config) as client:
            frame = client.info().frame
            chunks = nav2.ism_chunks(args.max_side, layer=args.layer, frame=frame)
            for ism in chunks:  # the layer field names the layer whatever the key
                client.publish_raw(f"ism/{args.layer}", codec.encode(ism))
    except Nav2MapError as exc:
        print(f"sogm-service import nav2: {args.yaml}: [{exc.code}] {exc}", file=sys.stderr)
        return 2
    except ClientError as exc:
        print(f"sogm-service import nav2: {exc}", file=sys.stderr)
        return 2
    g = nav2.geometry
    print(f"published {len(chunks)} ISM(s) of layer {args.layer!r}: {g.width}x{g.height} cells "
          f"at {g.resolution} m")
    return 0
