"""The tiled semantic map: a stack of log-odds layers kept in tiles of a fixed lattice.

Architecture, section 4 (docs/architecture.md#4-maps-and-tiles):
tile ``(i, j)`` holds its layers as ``(T, T)`` int16 planes of fixed-point
log-odds (:mod:`sogm_service.core.logodds`), one per layer written into that tile, allocated on
the layer's first write there (an absent plane is all unknown, 0): adding a layer costs one
plane in the tiles it reaches, never a copy of other layers.  A layer is added to the
map when its first ISM arrives; tiles are created on first write.  Writing an ISM resamples it
straight into each tile it overlaps (no map-sized intermediate), so the cost is proportional to
the ISM's footprint.

Concurrency: the map is shared by ingestion workers, queries and checkpoints without a
map-wide lock, so a query never waits for an ISM to be fused.

* Every tile has its own lock, held only to add one tile's patch (Eq. 1), to copy a block out
  of it, or to snapshot it; the resampling of an ISM (the expensive part) runs without any lock.
  A reader sees each tile either before or after an ISM's patch, never halfway; an ISM that
  spans several tiles may be visible in one and not yet in the next for the duration of its
  fuse.
* A structure lock guards the tile dictionary, the stored set and the layer list: creating,
  loading, inserting and evicting tiles, adding layers.  It is never held while a tile's lock
  is awaited by a writer, so it cannot deadlock with them.
* Writers to one tile are serialised by its lock; callers that need a tile's ISMs applied in
  arrival order (the service's fuse workers own disjoint tiles) keep that order themselves.
* A fuse is transactional, in two phases (:meth:`TiledMap.fuse`): first every patch is
  computed and every tile got, created or loaded back and *pinned* (a pinned tile is not
  evicted), then the patches are added, each under its tile's lock only.  A failure in the
  first phase changes no tile: the tiles it created or loaded leave the map again.

The map is assembled from one class per job: :class:`~sogm_service.core.map.mapstate.MapState`
(layers, tiles, residency, the clock), :class:`~sogm_service.core.map.fusing.Fusing` (the fuse
transaction) and :class:`~sogm_service.core.map.reading.Reading` (samples, mosaics, gathers).

This module is pure (no I/O): persistence and the memory budget are the caller's business
through two hooks, ``loader`` (bring back a tile that is not resident) and the LRU order of
:meth:`TiledMap.least_recently_used`.
"""

from __future__ import annotations

from sogm_service.core.map.fusing import Fusing
from sogm_service.core.map.reading import Reading


class TiledMap(Fusing, Reading):
    """Semantic layers on a tile lattice, fused with Eq. 1 and sampled with Eq. 3-5."""
