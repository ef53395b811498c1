"""A moving object for the demo's forgetting layer: a person who walks
back and forth, and a detector on every robot that reports it into a ``person`` layer.

The person is not part of the world's grids (the laser and the camera do not see it), so the
other layers are exactly what they are without it.  The detector's ISM is cast on the map's
lattice (:mod:`sogm_service.adapters.laser_lattice` explains why): ``p_free`` ("no person
here") over what the robot sees within ``range_m``, ``p_occ`` over a disc of ``radius`` at the
person when it is within range and in line of sight (nothing taller than ``eye_height`` in
between).  What it sees is the line of sight at ``eye_height``, cast in ``rays`` directions:
a detector says nothing of the far side of a wall or a shelf (and nothing outside the
building), so the layer's known area is the one the robots could look at.  The map server
gives the layer a half-life (``[map] forget``), so the person's old positions fade toward
unknown while the latest stays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.sim.robots import SimStep
from sogm_service.sim.sensors import SensorIsm, first_hit, lookup
from sogm_service.sim.worlds import World


@dataclass(frozen=True)
class WalkingPerson:
    """Walks from ``a`` to ``b`` and back at ``speed`` m/s, starting at ``a`` at t = 0."""

    a: tuple[float, float]
    b: tuple[float, float]
    speed: float = 1.2

    def position(self, t: float) -> tuple[float, float]:
        length = math.dist(self.a, self.b)
        if length == 0:
            return self.a
        s = (self.speed * max(t, 0.0)) % (2 * length)
        f = (s if s <= length else 2 * length - s) / length
        return (self.a[0] + f * (self.b[0] - self.a[0]), self.a[1] + f * (self.b[1] - self.a[1]))


def warehouse_person(world: World) -> WalkingPerson | None:
    """Along the open strip between the staging area and the first shelf row (None for a
    world without one)."""
    staging_y = world.meta.get("staging_y")
    if staging_y is None:
        return None
    w, _ = world.geometry.size_m
    y = float(staging_y) + 1.5
    return WalkingPerson((3.0, y), (w - 3.0, y))


@dataclass(frozen=True)
class PersonDetector:
    """Reports :class:`WalkingPerson` ``person`` into layer ``layer`` (module docstring)."""

    person: WalkingPerson
    layer: str = "person"
    name: str = "people"
    range_m: float = 15.0
    radius: float = 0.3
    eye_height: float = 1.0
    resolution: float = 0.05
    p_free: float = 0.45
    p_occ: float = 0.85
    rays: int = 360

    def observe(self, world: World, step: SimStep) -> list[SensorIsm]:
        """The step's ISM, measured at the true pose and placed at the reported one."""
        px, py = self.person.position(step.stamp)
        seen = self._visible(world, step.true_pose, (px, py))
        # The person where this robot believes it is: its offset from the true pose, carried
        # over to the reported pose (odometry drift shifts it like every other ISM).
        rel = step.true_pose.inverse().transform_points(np.array([[px, py]]))
        at = step.pose.transform_points(rel)[0]
        res = self.resolution
        c0 = math.floor((step.pose.x - self.range_m) / res)
        r0 = math.floor((step.pose.y - self.range_m) / res)
        n = math.ceil(2 * self.range_m / res) + 1
        geom = GridGeometry(res, n, n, Pose2D(c0 * res, r0 * res, 0.0))
        centres = geom.cell_centers()
        dx, dy = centres[..., 0] - step.pose.x, centres[..., 1] - step.pose.y
        p = np.full(geom.shape, 0.5, dtype=np.float32)
        p[self._in_sight(world, step, np.hypot(dx, dy), np.arctan2(dy, dx))] = self.p_free
        if seen:
            d_person = np.hypot(centres[..., 0] - at[0], centres[..., 1] - at[1])
            p[d_person <= self.radius] = self.p_occ
        return [SensorIsm(self.layer, geom, p, self.name)]

    def _in_sight(self, world: World, step: SimStep, dist: np.ndarray,
                  bearing: np.ndarray) -> np.ndarray:
        """Cells (by distance and map-frame bearing from the reported pose) within range and
        before the first obstacle at eye height in their direction (cast at the true pose)."""
        n = self.rays
        angles = np.arange(n, dtype=np.float64) * (2 * math.pi / n)  # robot frame
        reach = np.minimum(first_hit(world, step.true_pose, angles, self.range_m,
                                     self.eye_height, 0.0), self.range_m)
        rel = (bearing - step.pose.yaw) % (2 * math.pi)
        ray = np.rint(rel / (2 * math.pi / n)).astype(np.int64) % n
        return np.asarray(dist <= reach[ray])

    def _visible(self, world: World, pose: Pose2D, xy: tuple[float, float]) -> bool:
        d = math.hypot(xy[0] - pose.x, xy[1] - pose.y)
        if d > self.range_m:
            return False
        f = np.linspace(0.0, 1.0, max(2, math.ceil(d / world.geometry.resolution)))[:-1]
        pts = np.stack([pose.x + f * (xy[0] - pose.x), pose.y + f * (xy[1] - pose.y)], axis=1)
        heights, inside = lookup(world, pts, world.heights)
        return bool(np.all(~inside | (heights < self.eye_height)))
