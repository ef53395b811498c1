"""2-D poses, grid geometry and the tile lattice (architecture, section 4:
docs/architecture.md#4-maps-and-tiles).

Conventions (the same as nav_msgs/OccupancyGrid):

* A grid array is indexed ``[row, col]`` = ``[v, u]``; ``u`` runs along the grid's own x axis,
  ``v`` along its y axis.
* ``origin`` is the pose of the *corner* of cell (0, 0) in the parent frame; the grid's axes are
  rotated by ``origin.yaw``.
* Continuous cell coordinates put cell centres on integers (as OpenCV does): the centre of cell
  ``(u, v)`` is at grid-local metres ``((u + 0.5) * res, (v + 0.5) * res)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Matrix3 = npt.NDArray[np.float64]


def wrap_angle(angle: float) -> float:
    """``angle`` in ``[-pi, pi)``."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A planar pose: position (m) and heading (rad) in some parent frame."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def matrix(self) -> Matrix3:
        """Homogeneous 3x3 transform child -> parent."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_matrix(m: Matrix3) -> Pose2D:
        return Pose2D(float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))

    def compose(self, other: Pose2D) -> Pose2D:
        """``self ∘ other``: ``other`` expressed in ``self``'s frame, lifted to the parent."""
        return Pose2D.from_matrix(self.matrix() @ other.matrix())

    def inverse(self) -> Pose2D:
        return Pose2D.from_matrix(np.asarray(np.linalg.inv(self.matrix()), dtype=np.float64))

    def transform_points(self, xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Map ``(..., 2)`` points from this pose's frame to the parent frame."""
        pts = np.asarray(xy, dtype=np.float64)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        x = c * pts[..., 0] - s * pts[..., 1] + self.x
        y = s * pts[..., 0] + c * pts[..., 1] + self.y
        return np.stack([x, y], axis=-1)


@dataclass(frozen=True, slots=True)
class GridGeometry:
    """Where a ``height x width`` grid of square cells lies in its parent frame."""

    resolution: float
    width: int
    height: int
    origin: Pose2D = Pose2D()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"resolution must be a positive finite number, got {self.resolution}")
        if self.width < 0 or self.height < 0:
            raise ValueError(f"grid size must be non-negative, got {self.width}x{self.height}")

    @property
    def shape(self) -> tuple[int, int]:
        """Array shape ``(height, width)``."""
        return (self.height, self.width)

    @property
    def size_m(self) -> tuple[float, float]:
        return (self.width * self.resolution, self.height * self.resolution)

    def cell_to_world(self) -> Matrix3:
        """3x3 affine: continuous cell coordinates ``(u, v, 1)`` -> parent-frame metres."""
        r = self.resolution
        scale = np.array([[r, 0.0, 0.5 * r], [0.0, r, 0.5 * r], [0.0, 0.0, 1.0]])
        return self.origin.matrix() @ scale

    def world_to_cell(self) -> Matrix3:
        """3x3 affine: parent-frame metres -> continuous cell coordinates."""
        return np.asarray(np.linalg.inv(self.cell_to_world()), dtype=np.float64)

    def cell_centers(self) -> npt.NDArray[np.float64]:
        """``(height, width, 2)`` parent-frame coordinates of every cell centre."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        m = self.cell_to_world()
        x = m[0, 0] * u + m[0, 1] * v + m[0, 2]
        y = m[1, 0] * u + m[1, 1] * v + m[1, 2]
        return np.stack([x, y], axis=-1)

    def centre(self) -> tuple[float, float]:
        """Parent-frame ``(x, y)`` of the grid's centre (plain floats, no arrays: every ISM
        header asks, a cluster member's for every ISM it only checks)."""
        lx, ly = 0.5 * self.width * self.resolution, 0.5 * self.height * self.resolution
        o = self.origin
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        return (o.x + c * lx - s * ly, o.y + s * lx + c * ly)

    def corners(self) -> npt.NDArray[np.float64]:
        """``(4, 2)`` parent-frame corners of the grid's outer boundary."""
        w, h = self.size_m
        local = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        return self.origin.transform_points(local)

    def bounds(self) -> tuple[float, float, float, float]:
        """Axis-aligned ``(xmin, ymin, xmax, ymax)`` of the grid in the parent frame."""
        c = self.corners()
        return (float(c[:, 0].min()), float(c[:, 1].min()), float(c[:, 0].max()),
                float(c[:, 1].max()))

    def world_to_index(self, xy: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Integer ``(..., 2)`` cell indices ``(u, v)`` containing parent-frame points."""
        pts = np.asarray(xy, dtype=np.float64)
        local = self.origin.inverse().transform_points(pts)
        return np.floor(local / self.resolution).astype(np.int64)

    def subgrid(self, u0: int, v0: int, width: int, height: int) -> GridGeometry:
        """The geometry of the cell block ``[v0:v0+height, u0:u0+width]`` of this grid."""
        corner = self.origin.transform_points(
            np.array([u0 * self.resolution, v0 * self.resolution]))
        return GridGeometry(self.resolution, width, height,
                            Pose2D(float(corner[0]), float(corner[1]), self.origin.yaw))


def window_geometry(x: float, y: float, yaw: float, width_m: float, height_m: float,
                    resolution: float) -> GridGeometry:
    """A grid of ``width_m x height_m`` metres centred on ``(x, y)`` and rotated by ``yaw``.

    This is how sub-map requests name their window: centre pose, size, resolution.  The cell
    counts are rounded to the nearest whole cell (at least one).
    """
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    width = max(1, round(width_m / resolution))
    height = max(1, round(height_m / resolution))
    half = np.array([0.5 * width * resolution, 0.5 * height * resolution])
    centre = Pose2D(x, y, yaw)
    corner = centre.transform_points(-half)
    return GridGeometry(resolution, width, height, Pose2D(float(corner[0]), float(corner[1]), yaw))


@dataclass(frozen=True, slots=True)
class TileLattice:
    """The fixed tile lattice of a map frame: tile ``(i, j)`` covers
    ``[i*T*res, (i+1)*T*res) x [j*T*res, (j+1)*T*res)`` (architecture, section 4:
    docs/architecture.md#4-maps-and-tiles)."""

    resolution: float
    tile_size: int = 256

    def __post_init__(self) -> None:
        if self.tile_size <= 0 or self.tile_size & (self.tile_size - 1):
            raise ValueError(f"tile size must be a power of two, got {self.tile_size}")
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ValueError(f"resolution must be positive, got {self.resolution}")

    @property
    def span(self) -> float:
        """Edge length of one tile in metres."""
        return self.tile_size * self.resolution

    def tile_of(self, x: float, y: float) -> tuple[int, int]:
        """Index of the tile containing the point ``(x, y)``."""
        return (math.floor(x / self.span), math.floor(y / self.span))

    def tile_origin(self, i: int, j: int) -> Pose2D:
        return Pose2D(i * self.span, j * self.span, 0.0)

    def tile_geometry(self, i: int, j: int) -> GridGeometry:
        return GridGeometry(self.resolution, self.tile_size, self.tile_size,
                            self.tile_origin(i, j))

    def tiles_in_bounds(self, xmin: float, ymin: float, xmax: float,
                        ymax: float) -> list[tuple[int, int]]:
        """Every tile index whose area meets the axis-aligned box."""
        i0, j0 = self.tile_of(xmin, ymin)
        i1, j1 = self.tile_of(xmax, ymax)
        return [(i, j) for j in range(j0, j1 + 1) for i in range(i0, i1 + 1)]

    def tiles_overlapping(self, geometry: GridGeometry) -> list[tuple[int, int]]:
        """Every tile index that the (possibly rotated) grid may touch."""
        return self.tiles_in_bounds(*geometry.bounds())
