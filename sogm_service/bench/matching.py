"""Scan matching on synthetic floor plans (the ``matching`` row of ``sogm-service bench``).

:func:`synthetic_floorplan` also feeds the matching tests: a seeded map with the kind of
structure ORB latches onto.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import Pose2D
from sogm_service.core.matching.match import match_ism
from sogm_service.core.matching.params import MatchParams


def synthetic_floorplan(
    size: int = 512, seed: int = 0, wall: int = 2, l_occ: float = 3.0, l_free: float = -2.0
) -> npt.NDArray[np.int16]:
    """A structured, seeded floor plan as fixed log-odds: rooms, walls with doors, furniture.

    Rooms come from a random binary space partition; every wall gets a door; rooms get boxes
    and round obstacles (their insides unknown, as a laser never sees them).  For the tests and
    the benchmark of scan matching - a map with the kind of structure ORB latches onto.
    """
    rng = np.random.default_rng(seed)
    occ = np.zeros((size, size), np.uint8)
    cv2.rectangle(occ, (0, 0), (size - 1, size - 1), 1, wall)
    rooms: list[tuple[int, int, int, int]] = []
    _split(rng, (wall, wall, size - wall, size - wall), wall, occ, rooms)
    inside = np.zeros_like(occ)
    for x0, y0, x1, y1 in rooms:
        _furnish(rng, (x0, y0, x1, y1), occ, inside)
    l = np.where(occ > 0, l_occ, l_free)
    l[inside > 0] = 0.0
    return logodds.to_fixed(l)


def _split(
    rng: np.random.Generator, box: tuple[int, int, int, int], wall: int,
    occ: npt.NDArray[np.uint8], rooms: list[tuple[int, int, int, int]],
) -> None:
    """Recursive BSP: split boxes larger than ~100 cells with a wall that has a door."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    if max(w, h) < 100 or (max(w, h) < 180 and rng.random() < 0.3):
        rooms.append(box)
        return
    vertical = w >= h
    lo, hi = (x0, x1) if vertical else (y0, y1)
    cut = int(rng.integers(lo + (hi - lo) // 3, hi - (hi - lo) // 3))
    span = (y0, y1) if vertical else (x0, x1)
    door_w = int(rng.integers(14, 26))
    door = int(rng.integers(span[0] + 4, span[1] - door_w - 4))
    for a, b in ((span[0], door), (door + door_w, span[1])):
        if vertical:
            occ[a:b, cut:cut + wall] = 1
        else:
            occ[cut:cut + wall, a:b] = 1
    first = (x0, y0, cut, y1) if vertical else (x0, y0, x1, cut)
    second = (cut + wall, y0, x1, y1) if vertical else (x0, cut + wall, x1, y1)
    _split(rng, first, wall, occ, rooms)
    _split(rng, second, wall, occ, rooms)


def _furnish(
    rng: np.random.Generator, box: tuple[int, int, int, int], occ: npt.NDArray[np.uint8],
    inside: npt.NDArray[np.uint8],
) -> None:
    """A few boxes and round obstacles per room: outline occupied, interior unknown."""
    x0, y0, x1, y1 = box
    for _ in range(int(rng.integers(1, 5))):
        w, h = (int(v) for v in rng.integers(6, 22, size=2))
        if x1 - x0 <= w + 17 or y1 - y0 <= h + 17:
            continue
        u = int(rng.integers(x0 + 8, x1 - w - 8))
        v = int(rng.integers(y0 + 8, y1 - h - 8))
        if rng.random() < 0.6:
            cv2.rectangle(occ, (u, v), (u + w, v + h), 1, 2)
            cv2.rectangle(inside, (u + 2, v + 2), (u + w - 2, v + h - 2), 1, -1)
        else:
            r = max(3, min(w, h) // 2)
            cv2.circle(occ, (u + r, v + r), r, 1, 2)
            if r > 3:
                cv2.circle(inside, (u + r, v + r), r - 2, 1, -1)


def benchmark_match(size: int = 256, repeats: int = 10, seed: int = 0) -> dict[str, float]:
    """Time :func:`~sogm_service.core.matching.match.match_ism` for one ``size x size`` ISM
    misaligned by a few cells and degrees.

    For the bench suite (no printing): the ISM is cut from a synthetic floor plan, the window
    is :func:`~sogm_service.core.matching.match.match_window`'s margin around the claimed pose.
    """
    params = MatchParams()
    margin = params.window_margin(size, size)
    plan = synthetic_floorplan(max(3 * size, 512), seed)
    win_size = size + 2 * margin
    c = plan.shape[0] / 2.0
    truth = Pose2D(4.0, -3.0, math.radians(3.0))
    rot = cv2.getRotationMatrix2D((c, c), math.degrees(truth.yaw), 1.0)
    rot[:, 2] += np.array([truth.x, truth.y])
    moved = cv2.warpAffine(plan, rot, plan.shape[::-1], flags=cv2.INTER_NEAREST)
    lo = int(c) - size // 2
    ism = moved[lo:lo + size, lo:lo + size]
    w0 = int(c) - win_size // 2
    window = plan[w0:w0 + win_size, w0:w0 + win_size]
    times = []
    result = match_ism(ism, window, params)
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = match_ism(ism, window, params)
        times.append(time.perf_counter() - t0)
    arr = np.array(times)
    return {"size": float(size), "window": float(win_size), "repeats": float(repeats),
            "mean_s": float(arr.mean()), "min_s": float(arr.min()),
            "median_s": float(np.median(arr)), "accepted": float(result.accepted),
            "inliers": float(result.inliers)}
