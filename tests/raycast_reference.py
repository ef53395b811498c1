"""An independent ray-casting log-odds mapper (a test reference, not product code).

Written from the textbook, sharing no code with the project: per scan and per beam, classic
integer Bresenham (error-term form) on the map lattice (cell ``(u, v)`` covers
``[u r, (u+1) r) x [v r, (v+1) r)``) from the sensor's cell to the end point's cell.  Range
rules as the project's laser model: non-finite, non-positive and no-return readings
(``>= device_max``) are dropped; readings at or beyond ``usable`` are free up to ``usable``
(end cell included, no hit); a hit's cell is occupied, the cells before it free.  Each cell is
updated at most once per scan, occupied winning over free; log-odds in 1/1000 nat, clamped.

Also the two comparison measures: occupied IoU and free-where-unknown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt


@numba.njit(cache=False)
def _bresenham_scan(seen: npt.NDArray[np.int8], u0: int, v0: int, ue: npt.NDArray[np.int64],
                    ve: npt.NDArray[np.int64], hit: npt.NDArray[np.bool_]) -> None:
    """Mark one scan into ``seen`` (0 untouched, 1 free, 2 occupied) in grid indices."""
    h, w = seen.shape
    for b in range(ue.shape[0]):
        x, y = u0, v0
        x1, y1 = ue[b], ve[b]
        dx = abs(x1 - x)
        dy = -abs(y1 - y)
        sx = 1 if x < x1 else -1
        sy = 1 if y < y1 else -1
        err = dx + dy
        while True:
            at_end = x == x1 and y == y1
            if 0 <= x < w and 0 <= y < h:
                if at_end and hit[b]:
                    seen[y, x] = 2
                elif seen[y, x] == 0:
                    seen[y, x] = 1
            if at_end:
                break
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x += sx
            if e2 <= dx:
                err += dx
                y += sy


@dataclass
class ReferenceMap:
    """Log-odds (int32, 1/1000 nat) on the cells ``[c0, c0 + w) x [r0, r0 + h)``."""

    c0: int
    r0: int
    logodds: npt.NDArray[np.int32]
    observed: npt.NDArray[np.bool_]


def logit_fixed(p: float) -> int:
    return round(1000.0 * math.log(p / (1.0 - p)))


def reference_map(scans: list[tuple[float, float, float, npt.NDArray, npt.NDArray]],
                  resolution: float, usable: float, device_max: float, box: tuple[int, int,
                                                                                 int, int],
                  p_free: float = 0.3, p_occ: float = 0.8,
                  eps0: float = 0.001) -> ReferenceMap:
    """Scans ``(x, y, yaw, ranges, angles)`` (laser poses in the map frame) into a map of the
    cell box ``(c0, r0, w, h)``.  Increments as the project's ``occupancy_i8`` codes say:
    ``p_free`` and ``p_occ`` rounded to whole percent."""
    c0, r0, w, h = box
    l_free = logit_fixed(round(100 * p_free) / 100)
    l_occ = logit_fixed(round(100 * p_occ) / 100)
    clamp = logit_fixed(1.0 - eps0)
    state = np.zeros((h, w), dtype=np.int32)
    observed = np.zeros((h, w), dtype=bool)
    for x, y, yaw, ranges, angles in scans:
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        ok = np.isfinite(r) & (r > 0) & (r < device_max)
        r, a = r[ok], a[ok]
        hit = r < usable
        rc = np.minimum(r, usable)
        ex = x + rc * np.cos(yaw + a)
        ey = y + rc * np.sin(yaw + a)
        ue = np.floor(ex / resolution).astype(np.int64) - c0
        ve = np.floor(ey / resolution).astype(np.int64) - r0
        u0 = math.floor(x / resolution) - c0
        v0 = math.floor(y / resolution) - r0
        seen = np.zeros((h, w), dtype=np.int8)
        _bresenham_scan(seen, u0, v0, ue, ve, hit)
        state += np.where(seen == 2, l_occ, np.where(seen == 1, l_free, 0)).astype(np.int32)
        np.clip(state, -clamp, clamp, out=state)
        observed |= seen > 0
    return ReferenceMap(c0, r0, state, observed)


@dataclass(frozen=True)
class Comparison:
    occupied_iou: float
    free_where_unknown: int
    observed: int

    @property
    def free_where_unknown_frac(self) -> float:
        return self.free_where_unknown / max(self.observed, 1)


def compare(mapped: npt.NDArray[np.integer], ref: ReferenceMap) -> Comparison:
    """``mapped``: the project's log-odds on the reference's cell box."""
    occ_a = mapped > 0
    occ_b = ref.logodds > 0
    union = np.count_nonzero(occ_a | occ_b)
    iou = np.count_nonzero(occ_a & occ_b) / union if union else 1.0
    fwu = int(np.count_nonzero((mapped < 0) & ~ref.observed))
    return Comparison(float(iou), fwu, int(np.count_nonzero(ref.observed)))
