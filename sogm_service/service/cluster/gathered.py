"""A cluster member's view of the whole map for one query: its own tiles, and its peers' fetched
for the rest (:mod:`sogm_service.service.cluster.cluster`), through the two questions it asks
the cluster (:class:`TileSource`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt

from sogm_service.core.map.tile import Tile
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex


class TileSource(Protocol):
    """What a gathered map needs of the cluster: which tiles this member serves itself, and the
    others fetched from their owners (None: the owner has none; raises ``QueryError`` when no
    owner answers)."""

    def serves(self, index: TileIndex) -> bool: ...

    def fetch(self, indices: list[TileIndex]) -> dict[TileIndex, Tile | None]: ...


class GatheredMap(TiledMap):
    """A read-only view of the cluster's map for one query: this member's tiles where it
    serves them, the owners' (fetched once, before sampling) elsewhere."""

    def __init__(self, base: TiledMap, cluster: TileSource) -> None:
        super().__init__(base.name, base.frame, base.lattice, base.eps0)
        self._base = base
        self._cluster = cluster
        self.layers = base.layers
        self.set_forget(base._forget)  # decaying layers read as the base map reads them
        self._remote: dict[TileIndex, Tile | None] = {}

    def layer_id(self, layer: str, create: bool = False) -> int:
        return self._base.layer_id(layer, create)

    def known_tiles(self) -> set[TileIndex]:
        return self._base.known_tiles()

    def mosaic(self, box: tuple[int, int, int, int], layer_ids: list[int],
               now: float | None = None) -> npt.NDArray[np.int16]:
        c0, r0, w, h = box
        t = self.tile_size
        need = [(i, j) for j in range(r0 // t, (r0 + h - 1) // t + 1)
                for i in range(c0 // t, (c0 + w - 1) // t + 1)
                if not self._cluster.serves((i, j))]
        self._remote = self._cluster.fetch(need) if need else {}
        return super().mosaic(box, layer_ids, self._base.now() if now is None else now)

    def get_tile(self, index: TileIndex, create: bool = False) -> Tile | None:
        if index in self._remote:
            return self._remote[index]
        return self._base.get_tile(index)
