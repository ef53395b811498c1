"""What the server publishes to ROS 2: a region of the map as OccupancyGrids (pure, no zenoh).

:func:`publish_region` chooses the window: around the robots (``robots``: the box of their
positions plus ``radius_m``) or the whole known map (``known``), on the map's own cell lattice
(so sampling at map resolution is exact), shrunk about its centre to at most ``max_cells``
cells.  :func:`map_snapshot` samples every layer once in that window and fuses the chosen
layers by Eq. 6 (``max`` by default: P_M, a cell is as occupied as its most occupied class).
The caller holds the map lock around :func:`map_snapshot`.
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
