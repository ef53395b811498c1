"""Where the map meets storage and the fleet: tile store, checkpoints, eviction, tile manager.

Service layer (imports zenoh).  This first version keeps every tile in memory; the tile store
and the tile manager are wired in by the tiles issue.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.config import ServiceConfig
from sogm_service.geometry import TileLattice
from sogm_service.stats import Stats
from sogm_service.tiles import TiledMap, TileIndex

Guard = Callable[[str, Callable[[zenoh.Query], Any]], Callable[[zenoh.Query], None]]


class Persistence:
    def __init__(self, config: ServiceConfig, stats: Stats) -> None:
        self.config = config
        self.stats = stats
        self.lattice = TileLattice(config.map.resolution, config.map.tile_size)

    def open(self, tiled: TiledMap) -> None:
        """Index the store and tell the map which tiles exist on disk."""

    def load(self, i: int, j: int) -> tuple[list[str], npt.NDArray[np.int16], float] | None:
        return None

    def start(self, tiled: TiledMap, lock: threading.RLock) -> None:
        """Start background checkpointing."""

    def declare(self, session: zenoh.Session, guard: Guard) -> list[Any]:
        return []

    def touched(self, tiles: list[TileIndex], robot: str | None) -> None:
        """Tiles just written by an ISM from ``robot``."""

    def robot_pose(self, robot: str, x: float, y: float, stamp: float) -> None:
        """A robot's pose: the tile manager follows it."""

    def close(self, tiled: TiledMap, lock: threading.RLock, timeout: float) -> None:
        """Flush everything dirty and stop background work."""

    def stats_extra(self) -> dict[str, Any]:
        return {}
