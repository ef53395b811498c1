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
    serves them, the owners' (fetched once, before sampling) elsewhere.

    Both reading paths fetch first: :meth:`mosaic` (a window read at map resolution) and
    :meth:`read_cells` (a coarse window reads only the cells its warp interpolates from).  A
    tile neither served here nor fetched would read as unknown, a silently partial answer; so
    every tile a read touches is either this member's or its owner's, or the read raises."""

    def __init__(self, base: TiledMap, cluster: TileSource) -> None:
        super().__init__(base.name, base.frame, base.lattice, base.eps0)
        self._base = base
        self._cluster = cluster
        self.layers = base.layers
        self.set_forget(base._forget)  # decaying layers read as the base map reads them
        self._remote: dict[TileIndex, Tile | None] = {}

    def layer_id(self, layer: str, create: bool = False) -> int:
        return self._base.layer_id(layer, create)

    def half_life(self, lid: int) -> float | None:
        return self._base.half_life(lid)  # layer indices are the base map's

    def known_tiles(self) -> set[TileIndex]:
        return self._base.known_tiles()

    def mosaic(self, box: tuple[int, int, int, int], layer_ids: list[int],
               now: float | None = None) -> npt.NDArray[np.int16]:
        c0, r0, w, h = box
        t = self.tile_size
        self._fetch_for([(i, j) for j in range(r0 // t, (r0 + h - 1) // t + 1)
                         for i in range(c0 // t, (c0 + w - 1) // t + 1)])
        return super().mosaic(box, layer_ids, self._base.now() if now is None else now)

    def read_cells(self, u: npt.NDArray[np.int64], v: npt.NDArray[np.int64],
                   layer_ids: list[int], now: float | None = None) -> npt.NDArray[np.int16]:
        t = self.tile_size
        if u.size:
            pairs = np.unique(np.stack([u // t, v // t], axis=1), axis=0)
            self._fetch_for([(int(i), int(j)) for i, j in pairs.tolist()])
        return super().read_cells(u, v, layer_ids, self._base.now() if now is None else now)

    def _fetch_for(self, indices: list[TileIndex]) -> None:
        """Fetch the tiles of ``indices`` this member does not serve and has not fetched for
        this query yet (raises ``QueryError`` when an owner does not answer)."""
        need = [index for index in indices
                if index not in self._remote and not self._cluster.serves(index)]
        if need:
            self._remote.update(self._cluster.fetch(need))

    def get_tile(self, index: TileIndex, create: bool = False) -> Tile | None:
        if index in self._remote:
            return self._remote[index]
        return self._base.get_tile(index)
