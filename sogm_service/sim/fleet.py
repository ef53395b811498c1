"""A simulated fleet (or a replayed log) on Zenoh: every robot its own session, publishing
ISMs and poses.

Each robot of :func:`sogm_service.sim.robots.simulate` connects its own Zenoh session (client
mode, multicast scouting off, to the map server's endpoint, e.g. ``tcp/127.0.0.1:7447``) through
:class:`sogm_service.client.mapclient.MapClient` and publishes, per step,

* its reported pose on ``pose/<robot>`` (:class:`~sogm_service.wire.messages.PoseMessage`);
* each sensor ISM on ``ism/<robot>/<sensor>/<class>``
  (:class:`~sogm_service.wire.messages.IsmMessage`) with ``layer`` set to the class, so that
  every robot's ISMs of one class fuse into one map layer; with ``per_robot_layers`` it sends
  no ``layer`` and the server names the layer after the key's remainder
  (``<robot>/<sensor>/<class>``): every robot its own layers, which a class pattern
  (``*/*/<class>``) reads as one.

A robot whose link drops keeps publishing: while its ISM keys have no route to a server, its
client keeps the latest ISM per key and drops the rest (:mod:`sogm_service.client.offline`),
and sends what it kept when the route returns.  :class:`FleetStats` counts both, so
``isms = isms_sent + isms_dropped``; on closing, each robot waits up to ``flush_s`` for a
route for what it still holds, and asks the server's acknowledgements about what may have been
lost on the way (the newest of each key it never received is sent again).

ISMs travel as ``occupancy_i8`` (nav_msgs 0..100, -1 unknown) by default: one byte a cell and an
exact "unknown" (``prob_u8`` cannot say 0.5 exactly).  Puts use congestion control BLOCK
(MapClient's publishers), so large ISMs are never dropped.  Every session is closed on exit,
including on errors and on ``stop``.

:func:`replay_scans` publishes a recorded CARMEN log the same way, as one robot.

This is the only module of the simulator that talks to Zenoh.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sogm_service.adapters.carmen import DEFAULT_USABLE_RANGE, LaserScan, scan_ism
from sogm_service.adapters.laser import encode_occupancy_i8, encode_prob_u8, encode_prob_u8_v2
from sogm_service.adapters.laser_lattice import ISM_GRIDS, scan_ism_on_lattice
from sogm_service.client.mapclient import MapClient
from sogm_service.core.geometry import Pose2D
from sogm_service.sim.robots import SimStep, simulate
from sogm_service.sim.sensors import Sensor, SensorIsm
from sogm_service.sim.worlds import World
from sogm_service.wire import keys
from sogm_service.wire.compression import ZSTD, Compression

log = logging.getLogger(__name__)


@dataclass
class FleetStats:
    """What :func:`run_fleet` sent."""

    steps: int = 0
    isms: int = 0  # offered: every ISM the fleet produced
    poses: int = 0
    ism_bytes: int = 0
    wall_s: float = 0.0
    isms_dropped: int = 0  # by the offline policy (superseded, overflow, no route at the end)
    isms_flushed: int = 0  # sent late: held during an outage, then sent when the route returned
    outages: int = 0  # times a robot's ISM key lost its route
    isms_lost: int = 0  # never received (the server's acks say so), no copy to send again
    isms_resent: int = 0  # never received as first sent, so sent again (the newest per key)
    last_ids: dict[str, str] = field(default_factory=dict)  # ISM key -> its newest ISM's id

    @property
    def isms_sent(self) -> int:
        """ISMs put on the wire (``isms - isms_dropped``)."""
        return self.isms - self.isms_dropped


def ism_key(robot: str, ism: SensorIsm, prefix: str = "ism") -> str:
    """``<prefix>/<robot>/<sensor>/<class>``."""
    return keys.ism_key(prefix, robot, ism.sensor or "sensor", ism.layer)


def encode_cells(prob: np.ndarray, encoding: str) -> np.ndarray:
    """ISM probabilities -> the array to publish in ``encoding``."""
    if encoding == "occupancy_i8":
        return encode_occupancy_i8(prob)
    if encoding == "prob_u8":
        return encode_prob_u8(prob)
    if encoding == "prob_u8_v2":
        return encode_prob_u8_v2(prob)
    if encoding == "prob_f32":
        return np.asarray(prob, dtype=np.float32)
    raise ValueError(f"unknown ISM encoding {encoding!r}")


class RobotLink:
    """One robot's own Zenoh session and what it publishes."""

    def __init__(self, name: str, endpoint: str, *, ism_prefix: str = "ism",
                 pose_prefix: str = "pose", encoding: str = "occupancy_i8",
                 frame: str = "map", zenoh_config: Path | None = None,
                 compression: Compression | None = ZSTD, map_name: str = "default",
                 per_robot_layers: bool = False) -> None:
        self.name = name
        self.per_robot_layers = per_robot_layers  # no explicit layer: the key names it
        # The map's name: the offline policy asks this map's acks about ISMs on a lost link.
        self.client = MapClient.connect(endpoint, map_name=map_name, zenoh_config=zenoh_config)
        self.client.compression = compression  # None: raw ISMs (a baseline, older servers)
        self.ism_prefix = ism_prefix
        self.pose_prefix = pose_prefix
        self.encoding = encoding
        self.frame = frame

    def publish(self, step: SimStep, stamp: float, stats: FleetStats) -> None:
        """The step's reported pose, then its ISMs."""
        self.publish_pose(step.pose, stamp, stats)
        for ism in step.isms:
            self.publish_ism(ism, stamp, stats)

    def publish_pose(self, pose: Pose2D, stamp: float, stats: FleetStats) -> None:
        self.client.publish_pose(self.name, pose.x, pose.y, pose.yaw, stamp=stamp,
                                 frame=self.frame, key_prefix=self.pose_prefix)
        stats.poses += 1

    def publish_ism(self, ism: SensorIsm, stamp: float, stats: FleetStats) -> None:
        msg = self.client.publish_ism(
            ism_key(self.name, ism, self.ism_prefix), encode_cells(ism.prob, self.encoding),
            resolution=ism.geometry.resolution, origin=ism.geometry.origin,
            encoding=self.encoding, layer=None if self.per_robot_layers else ism.layer,
            frame=self.frame, stamp=stamp,
            robot=self.name)
        stats.isms += 1
        stats.ism_bytes += len(msg.data)
        if self.client.last_ism_id is not None:
            stats.last_ids[ism_key(self.name, ism, self.ism_prefix)] = self.client.last_ism_id

    def close(self, stats: FleetStats | None = None, flush_s: float = 0.0) -> None:
        """Send what the offline policy still holds (waiting up to ``flush_s`` for a route),
        add its counts to ``stats`` and close the session."""
        try:
            if flush_s > 0:  # what never arrived is sent again: wait out a silent link
                deadline = time.monotonic() + flush_s
                self.client.flush_offline(flush_s)
                self.client.settle_offline(max(deadline - time.monotonic(), 2.0))
        finally:
            self.client.close()  # drops (and counts) what is still held
            if stats is not None:
                offline = self.client.offline_stats()
                stats.isms_dropped += offline.dropped
                stats.isms_flushed += offline.flushed
                stats.outages += offline.outages
                stats.isms_lost += offline.lost_in_flight
                stats.isms_resent += offline.resent


def run_fleet(world: World, endpoint: str, *, robots: int = 3, duration_s: float = 20.0,
              rate_hz: float = 4.0, seed: int = 0, odom_noise: float = 0.0,
              sensors: Sequence[Sensor] | None = None, realtime: bool = True,
              encoding: str = "occupancy_i8", ism_prefix: str = "ism", pose_prefix: str = "pose",
              stop: threading.Event | None = None, speed: float = 1.0,
              zenoh_configs: Mapping[str, Path] | None = None,
              observers: Sequence[Callable[[SimStep], list[SensorIsm]]] = (),
              compression: Compression | None = ZSTD, flush_s: float = 5.0,
              map_name: str = "default", per_robot_layers: bool = False) -> FleetStats:
    """Drive a simulated fleet and publish it to the map server at ``endpoint``.

    ``speed`` is simulated seconds per wall second when ``realtime`` (3.0: three times faster).

    ``realtime`` paces steps at ``rate_hz`` on the wall clock (a live demo); otherwise steps go
    out as fast as they are simulated (tests, bulk loading).  Stamps are wall-clock seconds of
    the run's start plus simulated time.  ``stop`` ends the run early.  ``zenoh_configs`` gives
    robots their own Zenoh config (``robot1`` -> its JSON5, e.g. from ``sogm-service certs``)
    instead of a plain connection to ``endpoint``.  ``observers`` add ISMs to each step
    (e.g. :class:`sogm_service.sim.moving.PersonDetector`).  ``compression``: how the robots
    send their ISMs (zstd, or ``None`` for raw).  ``flush_s``: how long each robot waits at
    the end for a route for the ISMs it still holds after a drop-out.  ``map_name``: the
    server's map (the robots ask its acks).  ``per_robot_layers``: the ISMs carry no ``layer``,
    so the server names each after its key (``<robot>/<sensor>/<class>``).  Blocks until done.
    """
    names = [f"robot{i + 1}" for i in range(robots)]
    links: dict[str, RobotLink] = {}
    stats = FleetStats()
    t_wall0 = time.monotonic()
    t_epoch0 = time.time()
    try:
        for name in names:
            links[name] = RobotLink(name, endpoint, ism_prefix=ism_prefix,
                                    pose_prefix=pose_prefix, encoding=encoding,
                                    zenoh_config=(zenoh_configs or {}).get(name),
                                    compression=compression, map_name=map_name,
                                    per_robot_layers=per_robot_layers)
        for step in simulate(world, robots, duration_s, rate_hz, seed, odom_noise=odom_noise,
                             sensors=sensors):
            if stop is not None and stop.is_set():
                break
            for observe in observers:
                step.isms.extend(observe(step))
            if realtime:
                _sleep_until(t_wall0 + step.stamp / speed, stop)
            links[step.robot].publish(step, t_epoch0 + step.stamp, stats)
            stats.steps += 1
    finally:
        for link in links.values():
            try:
                link.close(stats, flush_s)
            except Exception:  # closing the rest matters more than one failure
                log.exception("closing %s's session failed", link.name)
    stats.wall_s = time.monotonic() - t_wall0
    return stats


def replay_scans(scans: Iterable[LaserScan], endpoint: str, *, robot: str = "carmen",
                 sensor: str = "laser", layer: str = "obstacle", resolution: float = 0.05,
                 usable_range: float = DEFAULT_USABLE_RANGE, speed: float = 1.0,
                 encoding: str = "occupancy_i8", ism_prefix: str = "ism",
                 pose_prefix: str = "pose", stop: threading.Event | None = None,
                 grid: str = "lattice", zenoh_config: Path | None = None) -> FleetStats:
    """Publish recorded scans (e.g. :func:`sogm_service.adapters.carmen.read_carmen`) as one robot.

    Per scan: the laser pose on ``pose/<robot>`` and its ISM
    (:func:`~sogm_service.adapters.carmen.scan_ism`) on ``ism/<robot>/<sensor>/<layer>``, stamped
    with the log's own stamps.  ``speed`` scales the log's pace (2.0 = twice as fast; 0 = as fast as
    possible).  The backbone of ``sogm-service replay carmen FILE``.

    ``grid = "lattice"`` (default) casts each ISM on the map's cells at ``resolution``
    (:func:`~sogm_service.adapters.laser_lattice.scan_ism_on_lattice`: the server adds it
    without resampling, so walls and beams stay as sharp as the scan; ``resolution`` must be the
    map's); ``"sensor"`` publishes the sensor-aligned grid the server resamples.
    """
    if grid not in ISM_GRIDS:
        raise ValueError(f"unknown ISM grid {grid!r}; use one of {ISM_GRIDS}")
    stats = FleetStats()
    t_wall0 = time.monotonic()
    link = RobotLink(robot, endpoint, ism_prefix=ism_prefix, pose_prefix=pose_prefix,
                     encoding=encoding, zenoh_config=zenoh_config)
    try:
        stamp0: float | None = None
        for scan in scans:
            if stop is not None and stop.is_set():
                break
            stamp0 = scan.stamp if stamp0 is None else stamp0
            if speed > 0:
                _sleep_until(t_wall0 + (scan.stamp - stamp0) / speed, stop)
            geom, p = (scan_ism_on_lattice(scan, resolution, usable_range) if grid == "lattice"
                       else scan_ism(scan, resolution, usable_range))
            link.publish_pose(scan.pose, scan.stamp, stats)
            link.publish_ism(SensorIsm(layer, geom, p, sensor), scan.stamp, stats)
            stats.steps += 1
    finally:
        link.close(stats, 5.0)
    stats.wall_s = time.monotonic() - t_wall0
    return stats


def _sleep_until(deadline: float, stop: threading.Event | None) -> None:
    delay = deadline - time.monotonic()
    if delay <= 0:
        return
    if stop is not None:
        stop.wait(delay)
    else:
        time.sleep(delay)
