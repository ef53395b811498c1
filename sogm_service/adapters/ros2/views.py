"""What the server publishes to ROS 2: a window of the map as OccupancyGrids (pure, no zenoh).

The window comes from :mod:`sogm_service.adapters.ros2.extent` (where, and how the extent stays
stable).  :func:`map_snapshot` samples every layer once in that window and fuses the chosen
layers by Eq. 6 (``max`` by default: P_M, a cell is as occupied as its most occupied class).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sogm_service.adapters.ros2.cdr import OccupancyGridFields
from sogm_service.adapters.ros2.convert import window_to_grid
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.map.tiles import TiledMap


@dataclass(frozen=True)
class MapSnapshot:
    """One publication: each layer's grid and the fused grid (None without layers)."""

    layers: dict[str, OccupancyGridFields] = field(default_factory=dict)
    fused: OccupancyGridFields | None = None


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
