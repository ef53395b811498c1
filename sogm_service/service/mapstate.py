"""The map and the lock that guards it, as one object every part of the server shares.

No part of the service is handed a bare lock: ingestion, queries, checkpoints, the fleet
tracker and replication all reach the map through :meth:`SharedMap.locked`, so who may touch
the map and when is decided in one place.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from sogm_service.core.tiles import TiledMap


class SharedMap:
    """One :class:`~sogm_service.core.tiles.TiledMap` and its lock (re-entrant: a loader
    called while fusing may read the map again)."""

    def __init__(self, tiled: TiledMap) -> None:
        self._tiled = tiled
        self._lock = threading.RLock()

    @contextmanager
    def locked(self) -> Iterator[TiledMap]:
        """The map, for as long as the ``with`` block runs; nobody else touches it meanwhile."""
        with self._lock:
            yield self._tiled

    @property
    def name(self) -> str:
        return self._tiled.name

    @property
    def frame(self) -> str:
        return self._tiled.frame
