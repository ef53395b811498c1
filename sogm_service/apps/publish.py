"""sogm-service publish-ism (one ISM from a file, fused before it returns) and
sogm-service schemas (the JSON Schema of every message)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from sogm_service.apps.options import (
    UsageError,
    angle_options,
    command,
    connection_args,
    one_line,
    yaw,
)
from sogm_service.apps.query import open_client


def add_parser(subparsers: Any) -> None:
    _add_publish(subparsers)
    p = command(subparsers, "schemas", "write the JSON Schema of every message")
    p.add_argument("--out", type=Path, default=Path("schemas"), metavar="DIR",
                   help="directory of the *.json files")
    p.add_argument("--check", action="store_true",
                   help="write nothing; exit 1 if the files differ from the models")
    p.set_defaults(handler=schemas)


def _add_publish(subparsers: Any) -> None:
    p = command(subparsers, "publish-ism",
                "send an ISM from a .npy or image file and wait until the server fused it",
                epilog="example: sogm-service publish-ism scan.npy --key "
                       "ism/robot1/laser/obstacle --resolution 0.05 --x 1 --y 2 --yaw-deg 90\n"
                       "Exit 0: fused (a query now sees it).  Exit 2: the server's reason "
                       "(e.g. stale_stamp: a --stamp its forgetting layer keeps nothing of), "
                       "or nothing heard back.")
    connection_args(p)
    p.add_argument("file", type=Path,
                   help=".npy of 2-D uint8 (prob_u8), int8 (occupancy_i8) or float32 "
                        "(prob_f32) cells, row 0 at the map's lowest y; or an image (grey: "
                        "dark = occupied, row 0 at the top)")
    p.add_argument("--key", default="ism/cli/manual",
                   help="key to publish on: ism/<robot>/<sensor>/<class>")
    p.add_argument("--resolution", type=float, required=True, metavar="M",
                   help="ISM cell size (m), required")
    p.add_argument("--x", type=float, default=0.0, metavar="M",
                   help="x of the corner of cell (0, 0) in the map frame (m)")
    p.add_argument("--y", type=float, default=0.0, metavar="M",
                   help="y of the corner of cell (0, 0) in the map frame (m)")
    angle_options(p, "grid")
    p.add_argument("--encoding", default=None,
                   choices=["prob_u8", "occupancy_i8", "prob_f32", "prob_u8_v2"],
                   help="cell encoding (default: from the dtype)")
    p.add_argument("--layer", default=None,
                   help="layer name (default: the key after ism/, e.g. robot1/laser/obstacle)")
    p.add_argument("--frame", default="map", help="frame of the pose (must be the map's)")
    p.add_argument("--stamp", type=float, default=None, metavar="SECONDS",
                   help="when the ISM was observed: Unix time in seconds, as the wire's stamp "
                        "(default: now); a layer that forgets weighs an ISM by its age and "
                        "refuses one too old to keep anything of")
    p.add_argument("--no-wait", action="store_true",
                   help="do not wait for the server's acknowledgement (fire and forget)")
    p.add_argument("--wait-timeout", type=float, default=15.0, metavar="S",
                   help="how long to wait until the ISM is fused (s)")
    p.set_defaults(handler=publish_ism)


def publish_ism(args: argparse.Namespace) -> int:
    import numpy as np

    from sogm_service.client.isms import build_ism
    from sogm_service.core.geometry import Pose2D

    data = read_grid(args.file)
    origin = Pose2D(args.x, args.y, yaw(args))
    if args.stamp is not None and not math.isfinite(args.stamp):
        raise UsageError("--stamp must be a finite number of seconds (Unix time)")
    stamp = time.time() if args.stamp is None else args.stamp
    # Checked before connecting: a bad file never waits for a network.
    build_ism(data, resolution=args.resolution, origin=origin, encoding=args.encoding,
              layer=args.layer, frame=args.frame, stamp=stamp)
    with open_client(args) as client:
        msg = client.publish_ism(args.key, data, resolution=args.resolution, origin=origin,
                                 encoding=args.encoding, layer=args.layer, frame=args.frame,
                                 stamp=stamp, wait=not args.no_wait,
                                 timeout=args.wait_timeout)
    state = "published" if args.no_wait else "fused"
    print(f"{state} {msg.width}x{msg.height} {msg.encoding} ISM on {args.key} "
          f"({np.asarray(data).nbytes} bytes, stamp {msg.stamp:.3f})")
    return 0


def read_grid(path: Path) -> Any:
    """The cells of a .npy array or of a grey image (dark = occupied, row 0 at the top)."""
    import cv2
    import numpy as np

    if not path.is_file():
        raise UsageError(f"{path}: no such file")
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise UsageError(f"{path} is not a readable .npy array: {one_line(exc)}") from None
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UsageError(f"cannot read {path} as an image (or use a .npy)")
    # Map rows grow upward, image rows downward.
    return np.ascontiguousarray((255 - img)[::-1])


def schemas(args: argparse.Namespace) -> int:
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
