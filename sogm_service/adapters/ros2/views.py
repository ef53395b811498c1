"""What the server publishes to ROS 2: a region of the map as OccupancyGrids (pure, no zenoh).

:func:`publish_region` chooses the window: around the robots (``robots``: the box of their
positions plus ``radius_m``, within the map's known tiles) or the whole known map (``known``),
on the map's own cell lattice
(so sampling at map resolution is exact), shrunk about its centre to at most ``max_cells``
cells.  :func:`stable_extent` makes the published extent stable, as nav2 and RViz need it: it
grows, in whole tiles, to hold each new window and never shrinks or moves, except when growing
would pass ``max_cells`` and the window's centre has left it.  :func:`map_snapshot` samples
every layer once in that window and fuses the chosen layers by Eq. 6 (``max`` by default:
P_M, a cell is as occupied as its most occupied class).  The caller holds the map lock around
:func:`map_snapshot`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sogm_service.adapters.ros2.cdr import OccupancyGridFields
from sogm_service.adapters.ros2.convert import window_to_grid
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.map.tiles import TiledMap

RegionMode = Literal["robots", "known"]


@dataclass(frozen=True)
class MapSnapshot:
    """One publication: each layer's grid and the fused grid (None without layers)."""

    layers: dict[str, OccupancyGridFields] = field(default_factory=dict)
    fused: OccupancyGridFields | None = None


MARGIN_TILES = 1
"""How far beyond the known tiles a region around the robots may reach (tiles)."""


def publish_region(tiled: TiledMap, robots: Iterable[tuple[float, float]] = (), *,
                   mode: RegionMode = "robots", radius_m: float = 20.0,
                   max_cells: int = 2048 * 2048) -> GridGeometry | None:
    """The window to publish, on the map's cell lattice; None when there is nothing."""
    res = tiled.lattice.resolution
    if mode == "robots":
        pts = np.asarray(list(robots), dtype=np.float64).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) == 0:
            return None
        lo, hi = pts.min(axis=0) - radius_m, pts.max(axis=0) + radius_m
        b = tiled.bounds()
        if b is None:
            return None
        # Near where the map has tiles: far beyond them every cell is unknown and costs the
        # subscribers bytes for nothing; a margin of MARGIN_TILES lets the known map grow
        # before the published extent must (each growth is a whole grid on every topic).
        span = tiled.lattice.span
        lo = np.maximum(lo, np.array(b[:2]) - MARGIN_TILES * span)
        hi = np.minimum(hi, np.array(b[2:]) + MARGIN_TILES * span)
        if (hi <= lo).any():
            return None
    else:
        b = tiled.bounds()
        if b is None:
            return None
        lo, hi = np.array(b[:2]), np.array(b[2:])
    u0, v0 = math.floor(lo[0] / res), math.floor(lo[1] / res)
    w = max(1, math.ceil(hi[0] / res) - u0)
    h = max(1, math.ceil(hi[1] / res) - v0)
    if w * h > max_cells:  # shrink about the centre, keeping the aspect
        f = math.sqrt(max_cells / (w * h))
        nw, nh = max(1, math.floor(w * f)), max(1, math.floor(h * f))
        u0 += (w - nw) // 2
        v0 += (h - nh) // 2
        w, h = nw, nh
    return GridGeometry(res, w, h, Pose2D(u0 * res, v0 * res, 0.0))


Cells = tuple[int, int, int, int]  # u0, v0, u1, v1 on the map's cell lattice


def _cells(g: GridGeometry) -> Cells:
    u0, v0 = round(g.origin.x / g.resolution), round(g.origin.y / g.resolution)
    return u0, v0, u0 + g.width, v0 + g.height


def _geometry(c: Cells, res: float) -> GridGeometry:
    return GridGeometry(res, c[2] - c[0], c[3] - c[1], Pose2D(c[0] * res, c[1] * res, 0.0))


def _round_out(c: Cells, step: int) -> Cells:
    return (c[0] // step * step, c[1] // step * step, -(-c[2] // step) * step,
            -(-c[3] // step) * step)


def _area(c: Cells) -> int:
    return (c[2] - c[0]) * (c[3] - c[1])


def stable_extent(current: GridGeometry | None, needed: GridGeometry, *, step: int,
                  max_cells: int) -> GridGeometry:
    """The extent to publish, given the one published so far and the window needed now.

    It stays ``current`` while that holds ``needed``; otherwise it grows to the union of both,
    rounded out to ``step`` cells (the tile size: the origin stays on the tile lattice).  When
    the union passes ``max_cells``, ``current`` stays while it still holds the centre of
    ``needed``, and only then is the extent placed anew on ``needed`` (rounded out, if that
    stays within ``max_cells``).  Every change of the result is a new grid for the subscribers.
    """
    res = needed.resolution
    need = _cells(needed)
    if current is not None and current.resolution == res:
        cur = _cells(current)
        if cur[0] <= need[0] and cur[1] <= need[1] and need[2] <= cur[2] and need[3] <= cur[3]:
            return current
        union = (min(cur[0], need[0]), min(cur[1], need[1]), max(cur[2], need[2]),
                 max(cur[3], need[3]))
        for c in (_round_out(union, step), union):
            if _area(c) <= max_cells:
                return _geometry(c, res)
        cu, cv = (need[0] + need[2]) / 2, (need[1] + need[3]) / 2
        if cur[0] <= cu < cur[2] and cur[1] <= cv < cur[3]:
            return current
    placed = _round_out(need, step)
    return _geometry(placed if _area(placed) <= max_cells else need, res)


def map_snapshot(tiled: TiledMap, window: GridGeometry, *, frame: str | None = None,
                 stamp: float = 0.0, layers: Sequence[str] | None = None,
                 fused_layers: Sequence[str] | None = None,
                 method: Literal["max", "bayes"] = "max",
                 publish_layers: bool = True) -> MapSnapshot:
    """Sample the layers into ``window`` (nearest: the window is on the lattice) and fuse.

    ``layers``: which layers to publish one by one (default all); ``fused_layers``: which to
    fuse (default all).  Unknown layer names are ignored.
    """
    names = list(tiled.layers)
    if not names:
        return MapSnapshot()
    stack = tiled.sample(window, names, "nearest")
    frame = frame or tiled.frame
    out: dict[str, OccupancyGridFields] = {}
    if publish_layers:
        wanted = set(layers) if layers is not None else set(names)
        for i, name in enumerate(names):
            if name in wanted:
                out[name] = window_to_grid(stack[i], window, kind="fixed", frame=frame,
                                           stamp=stamp)
    chosen = [i for i, n in enumerate(names) if fused_layers is None or n in fused_layers]
    fused = None
    if chosen:
        sub = stack[chosen]
        pooled = logodds.fuse_max(sub).astype(np.int32) if method == "max" \
            else logodds.fuse_bayes(sub)
        fused = window_to_grid(pooled, window, kind="fixed", frame=frame, stamp=stamp)
    return MapSnapshot(out, fused)
