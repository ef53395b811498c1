"""Offline mapping without Zenoh: simulated robots over a world, or a recorded laser log.

The same map as the server's, in one process: each ISM becomes fixed-point log-odds increments
(:func:`sogm_service.core.logodds.increments`) and is fused by Eq. 1 into a
:class:`~sogm_service.core.map.tiles.TiledMap` (biodds resampling by default, the paper's Eq. 5),
read back on the world's grid.  Used by the paper's Section IV evaluation and by tests.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt

from sogm_service.adapters.carmen import DEFAULT_USABLE_RANGE, LaserScan, scan_ism
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.resample import Interp
from sogm_service.sim.robots import simulate
from sogm_service.sim.sensors import Sensor, SensorIsm, default_sensors
from sogm_service.sim.worlds import World


def default_duration(world: World) -> float:
    """Seconds of driving that cover most of the world with one robot."""
    return 150.0 if world.kind == "tabletop" else 240.0


class OfflineMap:
    """The server's tiled map (:class:`~sogm_service.core.map.tiles.TiledMap`) in one process,
    read back on one grid: the layers in ``geometry``."""

    def __init__(self, geometry: GridGeometry, layers: Sequence[str],
                 eps0: float = logodds.DEFAULT_EPS0, interp: Interp = "biodds") -> None:
        self.geometry = geometry
        self.layers = list(layers)
        self.eps0 = eps0
        self.interp: Interp = interp
        self.tiled = TiledMap("offline", "map", TileLattice(geometry.resolution), eps0)
        for name in self.layers:
            self.tiled.layer_id(name, create=True)

    def fuse(self, ism: SensorIsm) -> None:
        """Eq. 1 for one ISM (unknown layers are ignored)."""
        if ism.layer not in self.layers:
            return
        inc = logodds.increments(ism.prob, logodds.Encoding.PROB_F32, self.eps0)
        self.tiled.fuse(ism.layer, inc, ism.geometry, self.interp)

    def fuse_all(self, isms: Iterable[SensorIsm]) -> None:
        for ism in isms:
            self.fuse(ism)

    def probabilities(self) -> npt.NDArray[np.float32]:
        """``(N, H, W)`` float32 probabilities on ``geometry`` (0.5 where nothing was
        observed)."""
        return logodds.fixed_to_prob(self.tiled.sample(self.geometry, self.layers, "nearest"))


def map_world(world: World, seed: int, *, robots: int = 1, duration_s: float | None = None,
              rate_hz: float = 2.0, odom_noise: float = 0.0,
              sensors: Sequence[Sensor] | None = None, interp: Interp = "biodds",
              eps0: float = logodds.DEFAULT_EPS0) -> tuple[list[str], npt.NDArray[np.float32]]:
    """Map ``world`` with simulated robots; returns layer names and an ``(N, H, W)`` float32
    probability stack on ``world.geometry``.

    Layers are the sensors' layers in mounting order, e.g. ``["obstacle", "floor", "table"]``
    for a table-top world.  Deterministic by ``seed``.
    """
    suite = default_sensors(world) if sensors is None else list(sensors)
    layers: list[str] = []
    for sensor in suite:
        layers.extend(name for name in sensor.layers() if name not in layers)
    sogm = OfflineMap(world.geometry, layers, eps0, interp)
    duration = default_duration(world) if duration_s is None else duration_s
    for step in simulate(world, robots, duration, rate_hz, seed, odom_noise=odom_noise,
                         sensors=suite):
        sogm.fuse_all(step.isms)
    return layers, sogm.probabilities()


def map_scans(scans: Iterable[LaserScan], resolution: float = 0.05,
              usable_range: float = DEFAULT_USABLE_RANGE,
              *, layer: str = "obstacle", margin: float = 1.0, interp: Interp = "biodds",
              eps0: float = logodds.DEFAULT_EPS0, p_free: float = 0.3, p_occ: float = 0.8,
              hit_width_cells: int = 1) -> tuple[GridGeometry, npt.NDArray[np.float32]]:
    """Fuse recorded laser scans (e.g. :func:`sogm_service.adapters.carmen.read_carmen`) offline.

    The device's no-return readings (``>= scan.max_range``) are dropped; readings beyond
    ``usable_range`` are free up to it.  The map is the axis-aligned grid around every beam end
    plus ``margin``; returns its geometry and the
    ``(H, W)`` float32 occupancy probabilities.  ``p_free``, ``p_occ`` and ``hit_width_cells``
    go to :func:`sogm_service.adapters.laser.laser_ism`.
    """
    isms = []
    for scan in scans:
        geom, p = scan_ism(scan, resolution, usable_range, p_free=p_free, p_occ=p_occ,
                           hit_width_cells=hit_width_cells)
        isms.append(SensorIsm(layer, geom, p, "laser"))
    if not isms:
        raise ValueError("no scans to map")
    corners = np.vstack([i.geometry.corners() for i in isms])
    lo = np.floor((corners.min(axis=0) - margin) / resolution) * resolution
    hi = np.ceil((corners.max(axis=0) + margin) / resolution) * resolution
    size = np.rint((hi - lo) / resolution).astype(int)
    geom = GridGeometry(resolution, int(size[0]), int(size[1]),
                        Pose2D(float(lo[0]), float(lo[1]), 0.0))
    sogm = OfflineMap(geom, [layer], eps0, interp)
    sogm.fuse_all(isms)
    return geom, sogm.probabilities()[0]
