"""The inverse sensor model (ISM) of a planar laser range finder (paper section III-B).

Each cell a beam passes through before its measured range is *free*, the cell where it ends is
*occupied*, everything beyond (and every cell no beam reaches) is *unknown* (P = 0.5 exactly,
i.e. a log-odds increment of 0, so fusing it leaves the map untouched).

Grid of the ISM (a decision the issue left open): **sensor-aligned**.  The returned geometry's
axes are the sensor's (``origin.yaw == sensor_pose.yaw``) and its box is the tightest whole-cell
box, in the sensor frame, around the sensor and every beam's end (clipped at ``max_range``),
padded by ``hit_width_cells``.  This is what a robot publishes in its own pose; the map server
warps it into the map (resampling handles the rotation).

Ranges at or beyond ``max_range`` are "no return": free up to ``max_range``, no hit.  So
``max_range`` is the ISM's *usable* range and may be smaller than the device's (e.g. 20 m for a
log whose device reports 81.9 m for no return); a tilted laser passes its floor-hit range.
Non-finite or non-positive ranges, and optionally the device's own "no return" readings
(``device_max_range``), are dropped: the beam contributes nothing.

Ray casting is vectorised: every beam is sampled at half-cell steps in one
``(beams, samples)`` array; no per-cell or per-beam Python loops.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry, Pose2D

UNKNOWN_P = 0.5

FloatArray = npt.NDArray[np.float32]


def scan_points(
    ranges: npt.ArrayLike, angles: npt.ArrayLike, max_range: float, min_range: float = 0.0,
    device_max_range: float = math.inf,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Beam geometry in the sensor frame.

    Returns ``(ends, valid, hit)``: ``(B, 2)`` end points with ranges clipped at ``max_range``,
    which beams are usable at all (finite, above ``min_range``, below ``device_max_range``),
    and which of them hit something (``range < max_range``).
    """
    r = np.asarray(ranges, dtype=np.float64).ravel()
    a = np.asarray(angles, dtype=np.float64).ravel()
    if r.shape != a.shape:
        raise ValueError(f"{r.size} ranges but {a.size} angles")
    valid = np.isfinite(r) & np.isfinite(a) & (r > max(min_range, 0.0)) & (r < device_max_range)
    hit = valid & (r < max_range)
    rc = np.where(valid, np.minimum(r, max_range), 0.0)
    ends = np.stack([rc * np.cos(a), rc * np.sin(a)], axis=1)
    return ends, valid, hit


def scan_endpoints_world(ranges: npt.ArrayLike, angles: npt.ArrayLike, sensor_pose: Pose2D,
                         max_range: float) -> npt.NDArray[np.float64]:
    """``(K, 2)`` map-frame points of the beams that hit something (``range < max_range``)."""
    ends, _, hit = scan_points(ranges, angles, max_range)
    return sensor_pose.transform_points(ends[hit])


def check_cast(resolution: float, max_range: float, hit_width_cells: int) -> None:
    """The arguments every laser ISM cast shares (sensor-aligned or on the map's lattice)."""
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be positive, got {resolution}")
    if not (max_range > 0 and math.isfinite(max_range)):
        raise ValueError(f"max_range must be positive and finite, got {max_range}")
    if hit_width_cells < 1:
        raise ValueError("hit_width_cells must be >= 1")


def ism_probabilities(shape: tuple[int, int], free: npt.NDArray[np.bool_],
                      occ: npt.NDArray[np.bool_], p_free: float,
                      p_occ: float) -> FloatArray:
    """Unknown (0.5) everywhere, ``p_free`` on free cells, ``p_occ`` on hits (occupied wins)."""
    p = np.full(shape, UNKNOWN_P, dtype=np.float32)
    p[free] = p_free
    p[occ] = p_occ
    return p


def laser_ism(
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
    """Ray-cast ISM of one scan: ``(geometry, float32 probabilities)``, unknown exactly 0.5.

    ``ranges`` (m) and ``angles`` (rad, sensor frame, counter-clockwise from the sensor's x
    axis) are 1-D of equal length; ``sensor_pose`` is the sensor's pose in the map frame.
    ``hit_width_cells`` (odd or even >= 1) widens each hit to a square of that many cells, for
    scans whose range noise exceeds a cell.  Occupied wins over free where beams disagree.
    Readings at or beyond ``device_max_range`` are the device's "no return" and are dropped
    (as gmapping does): glass and open doors would otherwise paint long free rays.
    """
    check_cast(resolution, max_range, hit_width_cells)
    ends, valid, hit = scan_points(ranges, angles, max_range, min_range, device_max_range)
    geom, corner = _sensor_box(ends[valid], sensor_pose, resolution, hit_width_cells)
    free = _free_mask(ends[valid], hit[valid], corner, geom)
    occ = _hit_mask(ends[hit], corner, geom, hit_width_cells)
    p = ism_probabilities(geom.shape, free, occ, p_free, p_occ)
    return geom, p


def _sensor_box(ends: npt.NDArray[np.float64], sensor_pose: Pose2D, resolution: float,
                pad_cells: int) -> tuple[GridGeometry, npt.NDArray[np.float64]]:
    """Whole-cell sensor-aligned box around the sensor and the beam ends.

    Returns the geometry and its corner in the sensor frame (metres).
    """
    pts = np.vstack([ends, np.zeros((1, 2))])
    lo = np.floor(pts.min(axis=0) / resolution) - pad_cells
    hi = np.floor(pts.max(axis=0) / resolution) + 1 + pad_cells
    width, height = (int(v) for v in (hi - lo))
    corner = lo * resolution
    origin = sensor_pose.compose(Pose2D(float(corner[0]), float(corner[1]), 0.0))
    return GridGeometry(resolution, width, height, origin), corner


def _free_mask(ends: npt.NDArray[np.float64], hit: npt.NDArray[np.bool_],
               corner: npt.NDArray[np.float64], geom: GridGeometry) -> npt.NDArray[np.bool_]:
    """Cells crossed by any beam, sampled at half-cell steps from the sensor to its end.

    Beams that hit stop a cell short of the hit: a surface seen at a grazing angle by other
    beams should not be erased by their last free samples.
    """
    mask = np.zeros(geom.shape, dtype=bool)
    if len(ends) == 0:
        return mask
    res = geom.resolution
    lengths = np.hypot(ends[:, 0], ends[:, 1])
    step = 0.5 * res
    t = np.arange(int(np.ceil(lengths.max() / step)) + 1) * step  # (S,)
    stop = lengths - np.where(hit, res, 0.0)
    keep = t[None, :] < stop[:, None]  # (B, S)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = ends / np.where(lengths > 0, lengths, 1.0)[:, None]
    u = np.floor((direction[:, 0:1] * t - corner[0]) / res).astype(np.int64)
    v = np.floor((direction[:, 1:2] * t - corner[1]) / res).astype(np.int64)
    inside = keep & (u >= 0) & (u < geom.width) & (v >= 0) & (v < geom.height)
    mask[v[inside], u[inside]] = True
    return mask


def _hit_mask(hits: npt.NDArray[np.float64], corner: npt.NDArray[np.float64],
              geom: GridGeometry, width_cells: int) -> npt.NDArray[np.bool_]:
    """Cells holding a beam end, widened to ``width_cells`` squares."""
    mask = np.zeros(geom.shape, dtype=np.uint8)
    if len(hits) == 0:
        return mask.astype(bool)
    uv = np.floor((hits - corner) / geom.resolution).astype(np.int64)
    u = np.clip(uv[:, 0], 0, geom.width - 1)
    v = np.clip(uv[:, 1], 0, geom.height - 1)
    mask[v, u] = 1
    if width_cells > 1:
        kernel = np.ones((width_cells, width_cells), np.uint8)
        return np.asarray(cv2.dilate(mask, kernel), dtype=bool)
    return mask.astype(bool)


def encode_prob_u8(p: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """Probabilities -> ``prob_u8`` codes (``round(p * 255)``).

    Note: 0.5 becomes 128, i.e. p = 0.502, a tiny but non-zero increment; prefer
    :func:`encode_occupancy_i8` or ``prob_f32`` when exact unknown matters.
    """
    return np.rint(np.clip(np.asarray(p, dtype=np.float64), 0, 1) * 255).astype(np.uint8)


def encode_occupancy_i8(p: npt.ArrayLike) -> npt.NDArray[np.int8]:
    """Probabilities -> ``occupancy_i8`` (nav_msgs 0..100), exact 0.5 -> -1 (unknown)."""
    q = np.asarray(p, dtype=np.float64)
    occ = np.rint(np.clip(q, 0, 1) * 100).astype(np.int8)
    occ[q == UNKNOWN_P] = -1
    return occ


def encode_prob_u8_v2(p: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """Probabilities -> ``prob_u8_v2`` codes: ``round(p * 254)``; exactly 0.5 and NaN -> 255
    (unknown: the cell is left untouched, as 127 would be too)."""
    q = np.asarray(p, dtype=np.float64)
    codes = np.rint(np.clip(np.nan_to_num(q, nan=0.5), 0, 1) * 254).astype(np.uint8)
    codes[(q == UNKNOWN_P) | np.isnan(q)] = 255
    return codes
