"""The laser inverse sensor model cast straight on the map's cell lattice.

:func:`sogm_service.adapters.laser.laser_ism` builds a *sensor-aligned* grid: the map server
then warps it into the map, and bilinear (biodds) interpolation spreads each ISM cell's
evidence into its neighbours (walls one cell thicker, long sparse beams two cells wide).
:func:`laser_ism_on_lattice` instead casts every beam on the map's own lattice and returns an
**axis-aligned** grid whose origin is a corner of a map cell, at the map's resolution: the
server recognises it as aligned (:func:`sogm_service.core.resample.lattice_offset`) and adds it
by slicing, so every ISM cell's evidence lands in exactly one map cell and nothing is
interpolated at all (it is also the server's fastest path).

Beams are traced from the sensor's cell to the end point's cell as a line of cells with one
cell per step along the major axis (the cells Bresenham's algorithm visits; rounding to even on
exact ties).  The same range rules as the sensor-aligned model: non-finite, non-positive and
no-return readings (``>= device_max_range``) are dropped; readings at or beyond ``max_range``
(the usable range) are free up to ``max_range`` with no hit; a hit's own cell is occupied and
the cells before it free; occupied wins where beams of one scan disagree.

The robot must know the map's resolution and lattice origin (the map frame's origin is a cell
corner): both are in ``sogm/<map>/info``.  Vectorised over ``(beams, steps)``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.adapters.carmen import DEFAULT_USABLE_RANGE, LaserScan
from sogm_service.adapters.laser import check_cast, ism_probabilities, scan_points
from sogm_service.core.geometry import GridGeometry, Pose2D

FloatArray = npt.NDArray[np.float32]

ISM_GRIDS: tuple[str, ...] = ("lattice", "sensor")
"""Where a laser ISM is cast: ``lattice`` (the map's cells, no resampling in the server) or
``sensor`` (a sensor-aligned grid the server resamples)."""


def laser_ism_on_lattice(
    ranges: npt.ArrayLike,
    angles: npt.ArrayLike,
    sensor_pose: Pose2D,
    resolution: float,
    max_range: float,
    *,
    p_free: float = 0.3,
    p_occ: float = 0.8,
    hit_width_cells: int = 1,
    min_range: float = 0.0,
    device_max_range: float = math.inf,
) -> tuple[GridGeometry, FloatArray]:
    """Ray-cast ISM of one scan on the map lattice of cell size ``resolution``.

    Same arguments and result as :func:`sogm_service.adapters.laser.laser_ism`, but the
    geometry has yaw 0 and its origin on a cell corner of the map frame (``origin.x`` and
    ``origin.y`` are whole multiples of ``resolution``), and the ISM covers the tightest box of
    map cells around the sensor and every beam end, padded by ``hit_width_cells``.
    """
    check_cast(resolution, max_range, hit_width_cells)
    ends, valid, hit = scan_points(ranges, angles, max_range, min_range, device_max_range)
    world = sensor_pose.transform_points(ends[valid])
    hits = hit[valid]
    s_cell = np.floor(np.array([sensor_pose.x, sensor_pose.y]) / resolution).astype(np.int64)
    e_cell = np.floor(world / resolution).astype(np.int64).reshape(-1, 2)
    cells = np.vstack([e_cell, s_cell[None, :]])
    lo = cells.min(axis=0) - hit_width_cells
    hi = cells.max(axis=0) + 1 + hit_width_cells
    width, height = (int(v) for v in (hi - lo))
    geom = GridGeometry(resolution, width, height,
                        Pose2D(float(lo[0]) * resolution, float(lo[1]) * resolution, 0.0))
    free = _free_cells(s_cell - lo, e_cell - lo, hits, geom.shape)
    occ = _hit_cells(e_cell[hits] - lo, geom.shape, hit_width_cells)
    p = ism_probabilities(geom.shape, free, occ, p_free, p_occ)
    return geom, p


def _free_cells(start: npt.NDArray[np.int64], ends: npt.NDArray[np.int64],
                hit: npt.NDArray[np.bool_], shape: tuple[int, int]) -> npt.NDArray[np.bool_]:
    """Cells on the line from ``start`` to each end cell, one per step along the major axis;
    a hit's own end cell is left out (it is occupied)."""
    mask = np.zeros(shape, dtype=bool)
    if len(ends) == 0:
        return mask
    d = ends - start[None, :]
    n = np.abs(d).max(axis=1)  # steps per beam
    k = np.arange(int(n.max()) + 1)  # (S,)
    last = np.where(hit, n - 1, n)  # the last step that is free
    keep = k[None, :] <= last[:, None]
    safe = np.maximum(n, 1)[:, None].astype(np.float64)
    u = start[0] + np.rint(d[:, 0:1] * k / safe).astype(np.int64)
    v = start[1] + np.rint(d[:, 1:2] * k / safe).astype(np.int64)
    mask[v[keep], u[keep]] = True
    return mask


def _hit_cells(cells: npt.NDArray[np.int64], shape: tuple[int, int],
               width_cells: int) -> npt.NDArray[np.bool_]:
    mask = np.zeros(shape, dtype=np.uint8)
    if len(cells) == 0:
        return mask.astype(bool)
    mask[cells[:, 1], cells[:, 0]] = 1
    if width_cells > 1:
        return np.asarray(cv2.dilate(mask, np.ones((width_cells, width_cells), np.uint8)),
                          dtype=bool)
    return mask.astype(bool)


def scan_ism_on_lattice(scan: LaserScan, resolution: float = 0.05,
                        usable_range: float = DEFAULT_USABLE_RANGE, *, p_free: float = 0.3,
                        p_occ: float = 0.8,
                        hit_width_cells: int = 1) -> tuple[GridGeometry, FloatArray]:
    """:func:`sogm_service.adapters.carmen.scan_ism` cast on the map lattice of cell size
    ``resolution`` (:func:`laser_ism_on_lattice`): the same range rules, no resampling."""
    return laser_ism_on_lattice(scan.ranges, scan.angles, scan.pose, resolution,
                                min(usable_range, scan.max_range), p_free=p_free, p_occ=p_occ,
                                hit_width_cells=hit_width_cells,
                                device_max_range=scan.max_range)
