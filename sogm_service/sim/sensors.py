"""Simulated sensors that turn a world + a pose into ISMs, as a real robot's would.

Every sensor *measures* from the robot's **true** pose (the world does not care what the robot
believes) and *publishes* its ISM placed at the robot's **reported** pose (what the robot
believes, odometry drift included): exactly the misalignment a real fleet's ISMs carry.

* :class:`TiltedLaser`: a 2-D laser pitched down by a few degrees.  A beam at horizontal range
  ``t`` is at height ``h - t tan(pitch)``; it stops at the first cell whose object reaches that
  height, or at the floor (``h / tan(pitch)``).  Floor returns are "no obstacle": the ISM takes
  free space up to just short of the floor range and no hit
  (:func:`sogm_service.adapters.laser.laser_ism`).
  Gaussian range noise.
* :class:`SemanticCamera`: a camera with a per-pixel semantic classifier, projected onto the
  ground: over its field-of-view footprint (near..far, +-hfov/2, cells not hidden behind objects
  taller than the camera) it reports a class per cell of its own, coarser grid; with probability
  ``confusion`` a cell's class is replaced by a uniformly chosen *other* class.  One ISM per
  reported class: ``p_hit`` where that class was seen, ``p_miss`` where another was, 0.5 outside
  the footprint.  Cells whose true label is ``unknown`` are never seen.

All ISM grids are sensor-aligned (origin yaw = sensor yaw) at the sensor's own resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from sogm_service.adapters.laser import laser_ism
from sogm_service.adapters.laser_lattice import laser_ism_on_lattice
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.sim.worlds import World

FloatArray = npt.NDArray[np.float32]


class SensorIsm(NamedTuple):
    """One ISM: the layer (class) it observes, where its grid lies, its probabilities."""

    layer: str
    geometry: GridGeometry
    prob: FloatArray
    sensor: str = ""


class Sensor(Protocol):
    """Anything mounted on a robot that produces ISMs."""

    @property
    def name(self) -> str: ...

    def layers(self) -> tuple[str, ...]: ...

    def isms(self, world: World, true_pose: Pose2D, reported_pose: Pose2D,
             rng: np.random.Generator) -> list[SensorIsm]: ...


def lookup(world: World, xy: npt.NDArray[np.float64],
           grid: npt.NDArray) -> tuple[npt.NDArray, npt.NDArray[np.bool_]]:
    """Values of a world-shaped ``grid`` at map-frame points, and which points lie inside."""
    uv = world.geometry.world_to_index(xy)
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u < world.geometry.width) & (v >= 0) & (v < world.geometry.height)
    vals = grid[np.where(inside, v, 0), np.where(inside, u, 0)]
    return vals, inside


def first_hit(world: World, pose: Pose2D, angles: npt.NDArray[np.float64], max_range: float,
              height_at: float, slope: float) -> npt.NDArray[np.float64]:
    """Horizontal range of each ray's first cell whose object reaches the ray's height.

    The ray is at ``height_at - slope * t`` at range ``t``; ``inf`` where nothing is hit within
    ``max_range`` (points outside the world hit nothing).  Sampled at half-cell steps,
    vectorised over ``(rays, samples)``.
    """
    step = 0.5 * world.geometry.resolution
    t = np.arange(1, math.ceil(max_range / step) + 1) * step
    local = np.stack([np.cos(angles)[:, None] * t, np.sin(angles)[:, None] * t], axis=-1)
    heights, inside = lookup(world, pose.transform_points(local), world.heights)
    blocked = inside & (heights >= (height_at - slope * t)[None, :])
    idx = np.argmax(blocked, axis=1)
    return np.where(blocked.any(axis=1), t[idx], np.inf)


@dataclass(frozen=True)
class TiltedLaser:
    """A planar laser pitched down by ``pitch`` rad, ``height`` m above the floor."""

    name: str = "laser"
    layer: str = "obstacle"
    mount: Pose2D = field(default_factory=Pose2D)
    height: float = 0.3
    pitch: float = math.atan(0.05)
    fov: float = math.radians(270)
    beams: int = 541
    device_range: float = 10.0
    resolution: float = 0.05
    range_noise: float = 0.02
    p_free: float = 0.3
    p_occ: float = 0.8
    hit_width_cells: int = 1
    # "sensor": a sensor-aligned ISM the server resamples; "lattice": cast on the map's cells
    # (``resolution`` must be the map's; no resampling).  The demo uses "lattice".
    grid: str = "sensor"

    @property
    def floor_range(self) -> float:
        """Horizontal distance at which the beams meet the floor (capped at the device's)."""
        if self.pitch <= 0:
            return self.device_range
        return min(self.height / math.tan(self.pitch), self.device_range)

    @property
    def usable_range(self) -> float:
        """Returns beyond this are taken as floor: ``floor_range`` minus 3 sigma and a cell."""
        return self.floor_range - 3 * self.range_noise - self.resolution

    def layers(self) -> tuple[str, ...]:
        return (self.layer,)

    def angles(self) -> npt.NDArray[np.float64]:
        return np.linspace(-self.fov / 2, self.fov / 2, self.beams)

    def scan(self, world: World, sensor_pose: Pose2D,
             rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
        """Simulated ``(ranges, angles)`` from the sensor's true pose (floor returns included)."""
        a = self.angles()
        r = first_hit(world, sensor_pose, a, self.floor_range, self.height,
                      math.tan(max(self.pitch, 0.0)))
        r = np.where(np.isfinite(r), r, self.floor_range)
        r = r + rng.normal(0.0, self.range_noise, size=r.shape)
        return r.astype(np.float32), a.astype(np.float32)

    def isms(self, world: World, true_pose: Pose2D, reported_pose: Pose2D,
             rng: np.random.Generator) -> list[SensorIsm]:
        ranges, angles = self.scan(world, true_pose.compose(self.mount), rng)
        cast = laser_ism_on_lattice if self.grid == "lattice" else laser_ism
        geom, p = cast(ranges, angles, reported_pose.compose(self.mount), self.resolution,
                       self.usable_range, p_free=self.p_free, p_occ=self.p_occ,
                       hit_width_cells=self.hit_width_cells)
        return [SensorIsm(self.layer, geom, p, self.name)]


@dataclass(frozen=True)
class SemanticCamera:
    """A ground-projected semantic camera: one ISM per class in ``classes``."""

    classes: tuple[str, ...]
    name: str = "camera"
    mount: Pose2D = field(default_factory=Pose2D)
    height: float = 1.8
    near: float = 0.5
    far: float = 5.0
    hfov: float = math.radians(70)
    resolution: float = 0.1
    confusion: float = 0.1
    p_hit: float = 0.75
    p_miss: float = 0.3

    def layers(self) -> tuple[str, ...]:
        return self.classes

    def grid(self, sensor_pose: Pose2D) -> GridGeometry:
        """The footprint's bounding box in the sensor frame, placed at ``sensor_pose``."""
        half = self.far * math.sin(self.hfov / 2)
        width = math.ceil((self.far - self.near * math.cos(self.hfov / 2)) / self.resolution)
        height = math.ceil(2 * half / self.resolution)
        x0 = self.near * math.cos(self.hfov / 2)
        return GridGeometry(self.resolution, width, height,
                            sensor_pose.compose(Pose2D(x0, -height * self.resolution / 2, 0.0)))

    def observe(self, world: World, sensor_pose: Pose2D,
                rng: np.random.Generator) -> tuple[GridGeometry, npt.NDArray[np.int64],
                                                   npt.NDArray[np.bool_]]:
        """Classified labels on the camera grid placed at the *true* pose, and visibility."""
        geom = self.grid(sensor_pose)
        centres = geom.cell_centers()
        local = sensor_pose.inverse().transform_points(centres)
        rng_m = np.hypot(local[..., 0], local[..., 1])
        bearing = np.arctan2(local[..., 1], local[..., 0])
        visible = (rng_m >= self.near) & (rng_m <= self.far) & (np.abs(bearing) <= self.hfov / 2)
        visible &= self._unoccluded(world, sensor_pose, rng_m, bearing)
        truth, inside = lookup(world, centres, world.labels)
        visible &= inside & (truth != 0)
        return geom, self._confuse(truth.astype(np.int64), len(world.classes) - 1, rng), visible

    def _unoccluded(self, world: World, sensor_pose: Pose2D, rng_m: npt.NDArray[np.float64],
                    bearing: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """Cells not behind an object taller than the camera (the occluder's face is seen)."""
        dtheta = 0.5 * world.geometry.resolution / self.far
        rays = math.ceil(self.hfov / dtheta) + 1
        angles = np.linspace(-self.hfov / 2, self.hfov / 2, rays)
        occ = first_hit(world, sensor_pose, angles, self.far, self.height, 0.0)
        idx = np.clip(np.rint((bearing + self.hfov / 2) / (self.hfov / (rays - 1))), 0, rays - 1)
        return np.asarray(rng_m <= occ[idx.astype(np.int64)] + self.resolution)

    def _confuse(self, truth: npt.NDArray[np.int64], n_classes: int,
                 rng: np.random.Generator) -> npt.NDArray[np.int64]:
        """With probability ``confusion`` swap a label for a uniformly chosen *other* class."""
        if n_classes < 2 or self.confusion <= 0:
            return truth
        flip = rng.random(truth.shape) < self.confusion
        offset = rng.integers(1, n_classes, size=truth.shape)
        other = (truth - 1 + offset) % n_classes + 1
        return np.where(flip, other, truth)

    def isms(self, world: World, true_pose: Pose2D, reported_pose: Pose2D,
             rng: np.random.Generator) -> list[SensorIsm]:
        _, seen, visible = self.observe(world, true_pose.compose(self.mount), rng)
        geom = self.grid(reported_pose.compose(self.mount))
        out = []
        for name in self.classes:
            k = world.class_index(name)
            p = np.where(seen == k, self.p_hit, self.p_miss)
            out.append(SensorIsm(name, geom, np.where(visible, p, 0.5).astype(np.float32),
                                 self.name))
        return out


def default_sensors(world: World) -> list[Sensor]:
    """The sensor suite a robot carries in ``world`` (chosen by ``world.kind``).

    * tabletop (1 cm map): a small robot's laser 12 cm up, meeting the floor at 1.2 m, 240 deg,
      1 cm ISM; a head camera 1 m up (it sees table tops; walls and nothing else occlude),
      0.15-1.2 m, 60 deg, 2 cm cells, classes floor + table, 10 % confusion.
    * warehouse (5 cm map) and anything else: a laser 30 cm up pitched ~2.9 deg (floor at 6 m),
      270 deg, 5 cm ISM; a mast camera 1.8 m up, 0.5-5 m, 70 deg, 10 cm cells, the world's
      non-structural classes, 10 % confusion.
    """
    if world.kind == "tabletop":
        return [
            TiltedLaser(mount=Pose2D(0.03, 0.0, 0.0), height=0.12, pitch=math.atan(0.1),
                        fov=math.radians(240), beams=481, device_range=4.0, resolution=0.01,
                        range_noise=0.004),
            SemanticCamera(classes=("floor", "table"), height=1.0, near=0.15, far=1.2,
                           hfov=math.radians(60), resolution=0.02),
        ]
    classes = tuple(c for c in world.classes[1:] if c != "wall")
    return [
        TiltedLaser(mount=Pose2D(0.2, 0.0, 0.0)),
        SemanticCamera(classes=classes),
    ]
