"""sogm-service replay carmen|rosbag FILE: a recorded log replayed into a map server.

Each front-laser scan of a CARMEN log (FLASER or ROBOTLASER1, with its corrected pose) becomes
the ISM of a laser inverse sensor model (free along each beam, occupied at the hit, unknown
beyond) published on ism/<robot>/laser/obstacle with its pose on pose/<robot>, exactly as a
live robot would; a ROS bag's LaserScan (posed by /tf) and OccupancyGrid topics likewise.
Without --connect or --zenoh-config the server is embedded (in this process, on 127.0.0.1);
the resulting map is written as a PNG (and optionally .npy).  A log without any usable scan is
refused with one line and exit status 2; the summary counts every line type read and skipped.
"""

from __future__ import annotations

import argparse
import sys
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from sogm_service.apps.options import command, fail, require_extra, subcommands


@dataclass
class ReplayResult:
    scans: int
    isms_fused: int
    malformed_lines: int
    geometry: Any
    probabilities: npt.NDArray[np.float32]
    stats: Any = None  # the reader's CarmenStats: every line type read and skipped


class NoScansError(ValueError):
    """The log has no usable laser scan (no FLASER/ROBOTLASER1 line, all malformed, or
    ``limit <= 0``): nothing to replay.  ``str()`` is one line for the user."""


def _server_args(p: argparse.ArgumentParser) -> None:
    """Where the replay goes: an embedded server unless told a running one."""
    p.add_argument("--connect", default=None, metavar="ENDPOINT",
                   help="Zenoh endpoint of a running server (default: an embedded one)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config of a running server's site, honoured as is (e.g. "
                        "a robot's from 'sogm-service certs'); replaces --connect "
                        "(default: none)")
    p.add_argument("--map", default="default", help="map name of that server")


def add_parser(subparsers: Any) -> None:
    p = command(subparsers, "replay", "replay a CARMEN laser log or a ROS bag into a map",
                description=__doc__ or "")
    sub = subcommands(p, "format", "FORMAT")
    c = command(sub, "carmen", "a CARMEN log (FLASER or ROBOTLASER1 lines, gzip or plain)")
    c.add_argument("file", type=Path, help="the log (.gz or plain text)")
    _server_args(c)
    c.add_argument("--resolution", type=float, default=0.05, metavar="M",
                   help="ISM and map cell size (m)")
    c.add_argument("--limit", type=int, default=None, metavar="N",
                   help="replay at most this many scans (default: all)")
    c.add_argument("--speed", type=float, default=0.0, metavar="X",
                   help="pace relative to the log's stamps, 1 = real time (0: as fast as "
                        "possible)")
    c.add_argument("--robot", default="carmen", help="robot name of the scans' ISMs and poses")
    c.add_argument("--ism-grid", choices=["lattice", "sensor"], default="lattice",
                   help="cast each laser ISM on the map's cells (lattice: sharp, no "
                        "resampling; --resolution must be the map's) or on a sensor-aligned "
                        "grid the server resamples (sensor)")
    c.add_argument("--png", type=Path, default=Path("carmen-map.png"), metavar="FILE",
                   help="picture of the resulting map")
    c.add_argument("--npy", type=Path, default=None, metavar="FILE",
                   help="the map's probabilities as a float32 array (default: none)")
    b = command(sub, "rosbag", "a ROS 1 bag or a ROS 2 bag (sqlite3 or mcap): LaserScan + "
                               "/tf and OccupancyGrid topics (needs the ros2 extra)")
    b.add_argument("file", type=Path, help="the bag (a ROS 2 bag is its directory)")
    _server_args(b)
    b.add_argument("--map-frame", default="map", help="the TF frame of the map")
    b.add_argument("--resolution", type=float, default=0.05, metavar="M",
                   help="laser ISM cell size (m)")
    b.add_argument("--robot", default="rosbag", help="robot name of the laser scans")
    b.add_argument("--png", type=Path, default=Path("rosbag-map.png"), metavar="FILE",
                   help="picture of the resulting map")
    b.add_argument("--npy", type=Path, default=None, metavar="FILE",
                   help="the map's probabilities as a float32 array (default: none)")
    p.set_defaults(handler=run)


_ZENOH_CONFIG: ContextVar[Path | None] = ContextVar("zenoh_config", default=None)
"""The ``--zenoh-config`` of this replay: every session it opens (its robot's, its client's)
comes from that file, as it is."""


def main(argv: list[str] | None = None) -> int:
    """sogm-service replay with these arguments."""
    from sogm_service.apps import cli

    return cli.main(["replay", *(sys.argv[1:] if argv is None else argv)])


def run(args: argparse.Namespace) -> int:
    if args.zenoh_config is not None:  # a running server, reached as the file says
        args.connect = args.connect or f"(the endpoints of {args.zenoh_config})"
    token = _ZENOH_CONFIG.set(args.zenoh_config)
    try:
        return _replay(args)
    finally:
        _ZENOH_CONFIG.reset(token)


def _replay(args: argparse.Namespace) -> int:
    if not args.file.exists():
        return fail(args.command_words, f"no such file {args.file}")
    if args.format == "rosbag":
        require_extra("ros2", "replay rosbag")
    try:
        if args.format == "rosbag":
            result = replay_rosbag(args.file, endpoint=args.connect, map_name=args.map,
                                   resolution=args.resolution, robot=args.robot,
                                   map_frame=args.map_frame)
        else:
            result = replay_carmen(args.file, endpoint=args.connect, map_name=args.map,
                                   resolution=args.resolution, limit=args.limit,
                                   speed=args.speed, robot=args.robot, grid=args.ism_grid)
    except NoScansError as exc:
        return fail(args.command_words, f"{args.file}: {exc}")
    _write(result, args.png, args.npy)
    g = result.geometry
    print(f"replayed {result.scans} scans ({result.malformed_lines} malformed lines skipped); "
          f"{result.isms_fused} ISMs fused; map {g.width}x{g.height} cells at {g.resolution} m")
    if result.stats is not None:
        print(result.stats.summary())
    print(f"wrote {args.png}" + (f" and {args.npy}" if args.npy else ""))
    return 0


def replay_rosbag(path: Path, *, endpoint: str | None = None, map_name: str = "default",
                  resolution: float = 0.05, robot: str = "rosbag",
                  map_frame: str = "map") -> ReplayResult:
    """Replay a ROS bag: ``LaserScan`` (posed by ``/tf``) as laser ISMs of ``robot``,
    ``OccupancyGrid`` topics as ISMs as they are, into ``endpoint`` or an embedded server."""
    from sogm_service.adapters.rosbag import BagGrid, BagReader, BagScan

    with BagReader(path, map_frame=map_frame) as reader:
        items = list(reader)
        stats = reader.stats
    scans = [i.scan for i in items if isinstance(i, BagScan)]
    grids = [i for i in items if isinstance(i, BagGrid)]
    if not scans and not grids:
        raise NoScansError(f"no localised LaserScan and no OccupancyGrid to replay ({stats})")

    def publish(ep: str) -> None:
        from sogm_service.client.mapclient import MapClient
        from sogm_service.sim.fleet import replay_scans
        from sogm_service.wire import codec

        if scans:
            replay_scans(scans, ep, robot=robot, resolution=resolution, speed=0.0,
                         zenoh_config=_ZENOH_CONFIG.get())
        with MapClient.connect(ep, map_name=map_name, zenoh_config=_ZENOH_CONFIG.get()) as client:
            for grid in grids:
                client.publish_raw(f"ism/{grid.layer}", codec.encode(grid.ism))

    return _with_server(endpoint, map_name, resolution, lambda ep: _collect(
        ep, publish, len(scans) + len(grids), scans, grids, map_name, resolution, robot,
        stats))


def _with_server(endpoint: str | None, map_name: str, resolution: float,
                 run: Any) -> ReplayResult:
    """``run(endpoint)`` against ``endpoint``, or against an embedded server on 127.0.0.1."""
    if endpoint is not None:
        result: ReplayResult = run(endpoint)
        return result
    from sogm_service.client.session import free_tcp_endpoint
    from sogm_service.service.config import ServiceConfig
    from sogm_service.service.server.server import MapServer

    local = free_tcp_endpoint()
    config = ServiceConfig.model_validate({"map": {"name": map_name, "resolution": resolution},
                                           "zenoh": {"listen": [local]}})
    server = MapServer(config).start()
    try:
        result = run(local)
    finally:
        server.stop()
    return result


def _collect(endpoint: str, publish: Any, n: int, scans: list[Any], grids: list[Any],
             map_name: str, resolution: float, robot: str, stats: Any) -> ReplayResult:
    """Publish, wait until the server handled every ISM, and read back the map's extent."""
    from sogm_service.client.mapclient import MapClient

    publish(endpoint)
    with MapClient.connect(endpoint, map_name=map_name, timeout=30.0,
                           zenoh_config=_ZENOH_CONFIG.get()) as client:
        fused = _wait_fused(client, n)
        info = client.info()
        if not info.layers or info.bounds is None:
            raise NoScansError(f"the server fused none of the {n} ISMs")
        layer = f"{robot}/laser/obstacle" if scans else grids[0].layer
        layer = layer if layer in info.layers else info.layers[0]
        xmin, ymin, xmax, ymax = info.bounds
        window = _bounds_window(scans, resolution) if scans else dict(
            x=(xmin + xmax) / 2, y=(ymin + ymax) / 2, yaw=0.0, width=xmax - xmin,
            height=ymax - ymin, resolution=resolution, interp="nearest")
        sub = client.submap(**window, layers=[layer], encoding="prob_f32")
    return ReplayResult(len(scans) + len(grids), fused, 0, sub.geometry,
                        sub.probabilities()[0], stats)


def replay_carmen(path: Path, *, endpoint: str | None = None, map_name: str = "default",
                  resolution: float = 0.05, limit: int | None = None, speed: float = 0.0,
                  robot: str = "carmen", grid: str = "lattice") -> ReplayResult:
    """Replay a log into the server at ``endpoint`` (or an embedded one); return the map.
    ``grid``: where the laser ISMs are cast (:func:`sogm_service.sim.fleet.replay_scans`)."""
    from sogm_service.adapters.carmen import CarmenStats, read_carmen

    stats = CarmenStats()
    scans = list(read_carmen(path, limit=limit, stats=stats))
    if not scans:
        raise NoScansError("no usable laser scans (FLASER or ROBOTLASER1) to replay; "
                           + ("--limit is 0; " if limit is not None and limit <= 0 else "")
                           + stats.summary())
    if endpoint is not None:
        return _replay_into(scans, endpoint, map_name, resolution, speed, robot, stats, grid)
    from sogm_service.client.session import free_tcp_endpoint
    from sogm_service.service.config import ServiceConfig
    from sogm_service.service.server.server import MapServer

    endpoint = free_tcp_endpoint()
    config = ServiceConfig.model_validate({"map": {"name": map_name, "resolution": resolution},
                                           "zenoh": {"listen": [endpoint]}})
    server = MapServer(config).start()
    try:
        result = _replay_into(scans, endpoint, map_name, resolution, speed, robot, stats, grid)
    finally:
        server.stop()
    return result


def _replay_into(scans: list[Any], endpoint: str, map_name: str, resolution: float,
                 speed: float, robot: str, stats: Any, grid: str = "lattice") -> ReplayResult:
    from sogm_service.client.mapclient import MapClient
    from sogm_service.sim.fleet import replay_scans

    replay_scans(scans, endpoint, robot=robot, resolution=resolution, speed=speed, grid=grid,
                 zenoh_config=_ZENOH_CONFIG.get())
    with MapClient.connect(endpoint, map_name=map_name, timeout=30.0,
                           zenoh_config=_ZENOH_CONFIG.get()) as client:
        fused = _wait_fused(client, len(scans))
        layer = f"{robot}/laser/obstacle"
        info = client.info()
        if layer not in info.layers:
            if not info.layers:
                raise NoScansError(f"the server fused none of the {len(scans)} scans "
                                   f"({fused} ISMs fused); {stats.summary()}")
            layer = info.layers[0]
        window = _bounds_window(scans, resolution)
        sub = client.submap(**window, layers=[layer], encoding="prob_f32")
    return ReplayResult(len(scans), fused, stats.malformed, sub.geometry,
                        sub.probabilities()[0], stats)


def _wait_fused(client: Any, n: int, timeout: float = 120.0) -> int:
    import sys
    import time

    from tqdm import tqdm

    deadline = time.monotonic() + timeout
    # The server's progress through the scans, with the time left (a terminal only).
    with tqdm(total=n, desc="replay", unit="ISM", file=sys.stderr, disable=None,
              mininterval=0.25) as bar:
        while True:
            c = client.stats().counters
            done = c.get("isms_fused", 0) + c.get("isms_rejected", 0)
            bar.update(min(done, n) - bar.n)
            if done >= n or time.monotonic() > deadline:
                return int(c.get("isms_fused", 0))
            time.sleep(0.1)


def _bounds_window(scans: list[Any], resolution: float, margin: float = 10.0) -> dict[str, Any]:
    """An axis-aligned window around the trajectory plus ``margin`` metres (beam reach)."""
    xy = np.array([[s.pose.x, s.pose.y] for s in scans]) if scans else np.zeros((1, 2))
    lo = xy.min(axis=0) - margin
    hi = xy.max(axis=0) + margin
    centre = (lo + hi) / 2
    size = np.ceil((hi - lo) / resolution) * resolution
    return dict(x=float(centre[0]), y=float(centre[1]), yaw=0.0, width=float(size[0]),
                height=float(size[1]), resolution=resolution, interp="nearest")


def _write(result: ReplayResult, png: Path, npy: Path | None) -> None:
    from sogm_service.apps.render import save_grid_png

    save_grid_png(png, result.probabilities, result.geometry,
                  title=f"replay: {result.scans} scans, {result.isms_fused} fused")
    if npy is not None:
        np.save(npy, result.probabilities)
