"""Ground-truth worlds for the simulator, randomised by seed.

A :class:`World` is a grid (its :class:`~sogm_service.core.geometry.GridGeometry` places it in
the map
frame, origin at (0, 0) with yaw 0) holding per cell

* ``labels``: the ground-truth class index; ``classes[0]`` is always ``"unknown"`` (space the
  robots can never observe, e.g. behind the room's walls);
* ``heights``: the top of whatever stands on the cell in metres (0 for floor).  Sensors use it:
  the tilted laser hits a cell when the object there reaches the beam's height, and the camera
  cannot see past objects taller than itself.

Two generators:

* :func:`tabletop_world`: a ~3 x 3 m room at 1 cm like the paper's Section IV scenarios (Fig. 9):
  classes unknown / floor / table / obstacle; walls count as ``obstacle``.
* :func:`warehouse_world`: a 60 x 40 m site at 5 cm with walls, pillars, shelf rows with aisles
  and cross-aisles, and a staging area with pallets on open floor.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry, Pose2D

UNKNOWN = "unknown"

TABLETOP_CLASSES: tuple[str, ...] = (UNKNOWN, "floor", "table", "obstacle")
WAREHOUSE_CLASSES: tuple[str, ...] = (UNKNOWN, "floor", "wall", "shelf", "pallet")


@dataclass(frozen=True)
class World:
    """A ground-truth world: class labels and object heights on one grid.

    ``kind`` (``"tabletop"`` or ``"warehouse"``) selects the default sensor suite and robot size
    (:func:`sogm_service.sim.sensors.default_sensors`).
    """

    labels: npt.NDArray[np.uint8]
    classes: tuple[str, ...]
    geometry: GridGeometry
    heights: npt.NDArray[np.float32]
    kind: str = "custom"
    seed: int = 0
    robot_radius: float = 0.1
    meta: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.classes[0] != UNKNOWN:
            raise ValueError("classes[0] must be 'unknown'")
        if self.labels.shape != self.geometry.shape or self.heights.shape != self.geometry.shape:
            raise ValueError("labels/heights do not match the geometry")

    def class_index(self, name: str) -> int:
        """Index of a class name (``ValueError`` if the world has no such class)."""
        return self.classes.index(name)

    def mask(self, name: str) -> npt.NDArray[np.bool_]:
        """Boolean ground truth of one class."""
        return np.asarray(self.labels == self.class_index(name))

    @property
    def occupied(self) -> npt.NDArray[np.bool_]:
        """Cells with something standing on them (what a horizontal laser at floor level hits)."""
        return np.asarray(self.heights > 0.0)

    def drivable(self, clearance: float | None = None) -> npt.NDArray[np.bool_]:
        """Known floor cells at least ``clearance`` (default: robot radius + 2 cells) from any
        obstacle or unknown cell: where a robot's centre may go."""
        if clearance is None:
            clearance = self.robot_radius + 2 * self.geometry.resolution
        free = (self.labels != 0) & ~self.occupied
        dist = cv2.distanceTransform(free.astype(np.uint8), cv2.DIST_L2, 5)
        return np.asarray(dist * self.geometry.resolution > clearance)


class _Canvas:
    """Labels + heights being painted with shapes given in world metres."""

    def __init__(self, geometry: GridGeometry) -> None:
        self.geometry = geometry
        self.labels = np.zeros(geometry.shape, dtype=np.uint8)
        self.heights = np.zeros(geometry.shape, dtype=np.float32)
        self._w2c = geometry.world_to_cell()

    def polygon_mask(self, corners: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """Cells whose centre lies inside a world-frame polygon (sub-cell accurate corners)."""
        uv = corners @ self._w2c[:2, :2].T + self._w2c[:2, 2]
        pts = np.rint(uv * 16).astype(np.int32).reshape(-1, 1, 2)  # 4 fractional bits
        img = np.zeros(self.geometry.shape, dtype=np.uint8)
        cv2.fillPoly(img, [pts], 1, lineType=cv2.LINE_8, shift=4)
        return img.astype(bool)

    def paint(self, mask: npt.NDArray[np.bool_], label: int, height: float) -> None:
        self.labels[mask] = label
        self.heights[mask] = height

    def rect(self, cx: float, cy: float, w: float, h: float, yaw: float, label: int,
             height: float) -> npt.NDArray[np.bool_]:
        """Paint a rotated rectangle; returns its mask."""
        mask = self.polygon_mask(rect_corners(cx, cy, w, h, yaw))
        self.paint(mask, label, height)
        return mask



def rect_corners(cx: float, cy: float, w: float, h: float, yaw: float) -> npt.NDArray[np.float64]:
    """``(4, 2)`` corners of a ``w x h`` rectangle centred on ``(cx, cy)`` rotated by ``yaw``."""
    local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) * 0.5
    return Pose2D(cx, cy, yaw).transform_points(local)


_Placement = tuple[float, float, float, float, float, int, float, float]
"""cx, cy, w, h, yaw, label, height, free margin around it (m)."""

_Sampler = Callable[[np.random.Generator], _Placement]


def _place_without_overlap(rng: np.random.Generator, canvas: _Canvas, allowed: npt.NDArray,
                           sample: _Sampler, tries: int = 400) -> bool:
    """Try random placements until one's footprint lies wholly inside ``allowed``; paint it."""
    for _ in range(tries):
        cx, cy, w, h, yaw, label, height, margin = sample(rng)
        grown = canvas.polygon_mask(rect_corners(cx, cy, w + 2 * margin, h + 2 * margin, yaw))
        if grown.any() and allowed[grown].all():
            canvas.rect(cx, cy, w, h, yaw, label, height)
            return True
    return False


def tabletop_world(seed: int, *, size_m: float = 3.0, resolution: float = 0.01) -> World:
    """A randomised table-top room like the paper's Section IV scenarios (Fig. 9).

    ``size_m`` square at ``resolution``: a walled room (random extent, wall thickness 5 cm,
    2 m high, class ``obstacle``) with unknown space outside, floor inside, 2-3 tables
    (0.5-0.9 x 0.4-0.7 m, random yaw, 0.75 m high) and 3-6 small box obstacles (6-35 cm,
    0.15-0.5 m high).  Objects keep 0.25 m from each other and from the walls so a small robot
    can drive around all of them; an object that finds no such place after many random tries
    is left out, so a crowded draw may hold fewer.
    """
    rng = np.random.default_rng([seed, 0x7AB1E])
    n = round(size_m / resolution)
    geom = GridGeometry(resolution, n, n, Pose2D())
    c = _Canvas(geom)
    floor, table, obstacle = 1, 2, 3
    x0, y0 = rng.uniform(0.05, 0.25, size=2)
    x1, y1 = size_m - rng.uniform(0.05, 0.25, size=2)
    wall = 0.05
    c.rect((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, 0.0, obstacle, 2.0)
    inner = c.rect((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0 - 2 * wall, y1 - y0 - 2 * wall, 0.0,
                   floor, 0.0)

    def free_floor() -> npt.NDArray[np.bool_]:
        return inner & (c.labels == floor)

    def table_sample(r: np.random.Generator) -> _Placement:
        return (float(r.uniform(x0, x1)), float(r.uniform(y0, y1)), float(r.uniform(0.5, 0.9)),
                float(r.uniform(0.4, 0.7)), float(r.uniform(-math.pi, math.pi)), table, 0.75,
                0.25)

    def obstacle_sample(r: np.random.Generator) -> _Placement:
        s = float(r.uniform(0.06, 0.25))
        return (float(r.uniform(x0, x1)), float(r.uniform(y0, y1)), s,
                s * float(r.uniform(0.6, 1.4)), float(r.uniform(-math.pi, math.pi)), obstacle,
                float(r.uniform(0.15, 0.5)), 0.25)

    for _ in range(int(rng.integers(2, 4))):
        _place_without_overlap(rng, c, free_floor(), table_sample)
    for _ in range(int(rng.integers(3, 7))):
        _place_without_overlap(rng, c, free_floor(), obstacle_sample)
    return World(c.labels, TABLETOP_CLASSES, geom, c.heights, kind="tabletop", seed=seed,
                 robot_radius=0.06, meta={"room_x0": float(x0), "room_y0": float(y0),
                                          "room_x1": float(x1), "room_y1": float(y1)})


def warehouse_world(seed: int, *, width_m: float = 60, height_m: float = 40,
                    resolution: float = 0.05) -> World:
    """A randomised warehouse: the fleet-scale site.

    Outer walls (0.3 m, 4 m high) with unknown space 0.5 m beyond them; a staging area of open
    floor along the south wall with pallets (1.2 x 0.8 m, 0.15-1.5 m high, class ``pallet``);
    the rest holds rows of shelves (1.0-1.2 m deep, 2.5 m high, class ``shelf``) along x,
    separated by 2.5-3.5 m aisles and broken by 3 m cross-aisles at random places; pillars
    (0.4 m, class ``wall``) on a regular grid where they miss the shelves.
    """
    rng = np.random.default_rng([seed, 0xAA12E])
    w = round(width_m / resolution)
    h = round(height_m / resolution)
    geom = GridGeometry(resolution, w, h, Pose2D())
    c = _Canvas(geom)
    floor, wall, shelf, pallet = 1, 2, 3, 4
    margin, thick = 0.5, 0.3
    c.rect(width_m / 2, height_m / 2, width_m - 2 * margin, height_m - 2 * margin, 0.0, wall, 4.0)
    ix0, iy0 = margin + thick, margin + thick
    ix1, iy1 = width_m - margin - thick, height_m - margin - thick
    c.rect((ix0 + ix1) / 2, (iy0 + iy1) / 2, ix1 - ix0, iy1 - iy0, 0.0, floor, 0.0)
    staging_y = iy0 + float(rng.uniform(7.0, 10.0))
    _shelf_rows(rng, c, ix0 + 3.0, ix1 - 3.0, staging_y + 3.0, iy1 - 3.0, shelf)
    _pillars(rng, c, ix0, ix1, iy0, iy1, wall)

    def pallet_sample(r: np.random.Generator) -> _Placement:
        yaw = float(r.choice([0.0, math.pi / 2])) + float(r.normal(0, 0.05))
        return (float(r.uniform(ix0, ix1)), float(r.uniform(iy0, staging_y)), 1.2, 0.8, yaw,
                pallet, float(r.uniform(0.15, 1.5)), 1.0)

    allowed = c.labels == floor
    for _ in range(int(rng.integers(15, 30))):
        _place_without_overlap(rng, c, allowed & (c.labels == floor), pallet_sample)
    return World(c.labels, WAREHOUSE_CLASSES, geom, c.heights, kind="warehouse", seed=seed,
                 robot_radius=0.35, meta={"staging_y": staging_y})


def _shelf_rows(rng: np.random.Generator, c: _Canvas, x0: float, x1: float, y0: float,
                y1: float, label: int) -> None:
    """Rows of shelves along x between ``y0`` and ``y1``, each broken by cross-aisles."""
    y = y0
    while True:
        depth = float(rng.uniform(1.0, 1.2))
        if y + depth > y1:
            return
        cuts = np.sort(rng.uniform(x0 + 4.0, x1 - 4.0, size=int(rng.integers(1, 3))))
        edges = [x0, *[v for cut in cuts for v in (cut - 1.5, cut + 1.5)], x1]
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if b - a > 1.0:
                c.rect((a + b) / 2, y + depth / 2, b - a, depth, 0.0, label, 2.5)
        y += depth + float(rng.uniform(2.5, 3.5))


def _pillars(rng: np.random.Generator, c: _Canvas, x0: float, x1: float, y0: float, y1: float,
             label: int) -> None:
    """Building pillars on a ~10 m grid, skipped where they would touch a shelf."""
    step = float(rng.uniform(9.0, 12.0))
    for px in np.arange(x0 + step / 2, x1 - 1.0, step):
        for py in np.arange(y0 + step / 2, y1 - 1.0, step):
            grown = c.polygon_mask(rect_corners(float(px), float(py), 2.4, 2.4, 0.0))
            if (c.labels[grown] == 1).all():
                c.rect(float(px), float(py), 0.4, 0.4, 0.0, label, 4.0)
