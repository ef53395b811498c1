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
from sogm_service.core.classes import LayerClass, fuse_classes, member_layers, resolve
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.map.tiles import TiledMap


@dataclass(frozen=True)
class MapSnapshot:
    """One publication: each layer's grid, the fused grid (None without layers) and nav2's
    filter masks by name (``keepout``, ``speed``: :mod:`sogm_service.adapters.ros2.filters`)."""

    layers: dict[str, OccupancyGridFields] = field(default_factory=dict)
    fused: OccupancyGridFields | None = None
    masks: dict[str, OccupancyGridFields] = field(default_factory=dict)


def _classes(entries: Sequence[str] | None, names: list[str]) -> list[LayerClass]:
    """The classes of ``entries`` (every layer its own when None) that match some layer."""
    if entries is None:
        return [LayerClass(n, (n,)) for n in names]
    return [c for c in resolve(entries, names, allow_empty=True) if c.members]


def map_snapshot(tiled: TiledMap, window: GridGeometry, *, frame: str | None = None,
                 stamp: float = 0.0, layers: Sequence[str] | None = None,
                 fused_layers: Sequence[str] | None = None,
                 method: Literal["max", "bayes"] = "max",
                 publish_layers: bool = True) -> MapSnapshot:
    """Sample the layers into ``window`` (nearest: the window is on the lattice) and fuse.

    ``layers``: what to publish one by one (default every layer); ``fused_layers``: what to
    pool into the fused map (default every layer).  An entry is a layer's name or a class
    pattern (:mod:`sogm_service.core.classes`: e.g. ``*/laser/obstacle``, the matching layers
    fused by the Bayesian rule into one grid named by the pattern); the fused map pools the
    classes.  Entries that match no layer (yet) are left out.
    """
    names = list(tiled.layers)
    if not names:
        return MapSnapshot()
    published = _classes(layers, names) if publish_layers else []
    pooled = _classes(fused_layers, names)
    read = member_layers([*published, *pooled])
    if not read:
        return MapSnapshot()
    stack = tiled.sample(window, read, "nearest")
    frame = frame or tiled.frame
    out: dict[str, OccupancyGridFields] = {}
    for cls, plane in zip(published, fuse_classes(stack, read, published), strict=True):
        out[cls.name] = window_to_grid(plane, window, kind="fixed", frame=frame, stamp=stamp)
    fused = None
    if pooled:
        sub = fuse_classes(stack, read, pooled)
        fused_plane = logodds.fuse_max(sub).astype(np.int32) if method == "max" \
            else logodds.fuse_bayes(sub)
        fused = window_to_grid(fused_plane, window, kind="fixed", frame=frame, stamp=stamp)
    return MapSnapshot(out, fused)
