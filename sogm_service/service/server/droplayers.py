"""Taking evidence back: the ``<prefix>/<map>/drop/<pattern>`` queryable removes every layer
whose name matches a glob pattern (``robot3/*``: :mod:`sogm_service.core.classes`, ``*``
crossing ``/``) from the map and from its store, and answers what it removed
(:class:`~sogm_service.wire.messages.DropLayersReply`).

The pattern travels in the key (:func:`~sogm_service.wire.keys.drop_chunks`), never in a
parameter or body, so Zenoh's access control decides who may drop what from the key alone: a
robot is allowed ``drop/<robot>/**`` (its own layers), an operator ``drop/**``
(docs/security.md).

What a drop does, in order (one drop at a time):

1. the matching layers leave the map (:meth:`~sogm_service.core.map.mapstate.MapState.drop_layers`):
   every resident tile loses their planes and gets a new version; a tile left without planes
   leaves the map;
2. with a store, every stored tile that is not resident is loaded back (the writer's queue
   first), which leaves the dropped layers out, and evicted again: a tile that held them is
   written back without them, one left without planes is forgotten;
3. the rewritten resident tiles are checkpointed, the writer flushed, then the files of the
   tiles left empty removed: when the reply says ``stored``, no file of the store holds the
   layers, so they do not come back after a restart, even one after a SIGKILL.

An ISM of a dropped layer that was being fused as the drop ran is removed with it; one that
arrives afterwards (the robot still publishing) starts the layer again, so stop or fix the
robot first.  A ROS 2 topic of the layer stays declared with its last grid.  A cluster member
refuses (``cluster_unsupported``): it holds only its share of the tiles and replicas of its
peers', so a drop on one member would come back from another.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from sogm_service.core.classes import member_layers, resolve
from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.stats import Stats, cut
from sogm_service.wire.errors import QueryError
from sogm_service.wire.keys import MapKeys, drop_pattern
from sogm_service.wire.messages import DropLayersReply

log = logging.getLogger(__name__)

FLUSH_TIMEOUT_S = 60.0
"""How long a drop waits for the writer to put its rewritten tiles on disk."""


class LayerDrop:
    """The drop queryable's handler (module docstring)."""

    def __init__(self, keys: MapKeys, tiled: TiledMap, tiles: Checkpointer, stats: Stats,
                 server_id: Callable[[], str], clustered: bool = False) -> None:
        self.keys = keys
        self.tiled = tiled
        self.tiles = tiles
        self.stats = stats
        self.server_id = server_id
        self.clustered = clustered
        self._one = threading.Lock()

    def on_query(self, q: zenoh.Query) -> DropLayersReply:
        """Refused from the key alone, before any work: ``bad_parameter`` (no pattern a key
        carries), ``cluster_unsupported``."""
        key = str(q.key_expr)
        try:
            pattern = drop_pattern(key, self.keys)
        except ValueError as exc:
            raise self._refuse("bad_parameter", str(exc), "pattern") from None
        if self.clustered:
            raise self._refuse("cluster_unsupported", "layers are dropped on a single server "
                                                      "only", "pattern")
        with self._one:
            return self.drop(pattern)

    def _refuse(self, code: str, message: str, parameter: str) -> QueryError:
        log.warning("layer drop refused (%s): %s", code, cut(message))
        return QueryError(code, message, parameter)

    def drop(self, pattern: str) -> DropLayersReply:
        """Remove the layers matching ``pattern`` (module docstring); nothing matching is an
        empty reply, not an error (a drop asked again finds nothing left)."""
        started = time.perf_counter()
        tiled = self.tiled
        names = member_layers(resolve([pattern], list(tiled.layers), allow_empty=True))
        gone, rewritten, emptied = tiled.drop_layers(names)
        stored = False
        try:
            if gone and self.tiles.writer is not None:
                rewritten += self._rewrite_stored(set(gone), emptied)
            stored = self._persist(emptied)
        finally:
            tiled.end_drop()
        self.stats.count("layers_dropped", len(gone))
        self.stats.count("drop_tiles_rewritten", len(rewritten))
        self.stats.count("drop_tiles_removed", len(emptied))
        if gone:
            log.info("dropped %d layers matching %r in %.2f s: %s; %d tiles rewritten, "
                     "%d removed", len(gone), pattern, time.perf_counter() - started,
                     cut(", ".join(gone)), len(rewritten), len(emptied))
        return DropLayersReply(map=tiled.name, server_id=self.server_id(), pattern=pattern,
                               layers=gone, tiles_rewritten=len(rewritten),
                               tiles_removed=len(emptied), stored=stored)

    def _rewrite_stored(self, gone: set[str], emptied: list[TileIndex]) -> list[TileIndex]:
        """Step 2: every stored tile that is not resident, loaded without the dropped layers
        and evicted again (written back if it held them); returns those rewritten and adds
        those left empty to ``emptied``."""
        tiled, writer = self.tiled, self.tiles.writer
        assert writer is not None
        rewritten: list[TileIndex] = []
        for index in tiled.not_resident():
            if index in tiled.tiles:  # loaded meanwhile: its load already left them out
                continue
            tile = tiled.get_tile(index)
            if tile is None or not tile.dirty:
                tiled.evict(index)  # it held none of them (a pinned tile stays resident)
                continue
            if not tile.planes:
                tiled.discard(index)
                emptied.append(index)
                continue
            if tiled.evict(index, before=self._submit) is not None:
                rewritten.append(index)
            if self.tiles.writer_full():
                writer.flush(FLUSH_TIMEOUT_S)
        return rewritten

    def _submit(self, snap: TileSnapshot) -> None:
        assert self.tiles.writer is not None
        self.tiles.writer.submit(snap.index[0], snap.index[1], snap.layers, snap.data,
                                 snap.stamp, token=snap.version, decay=snap.decay,
                                 applied=snap.applied)

    def _persist(self, emptied: list[TileIndex]) -> bool:
        """Step 3; True when the store holds the result (False without a store)."""
        writer, store = self.tiles.writer, self.tiles.store
        if writer is None or store is None:
            return False
        errors = writer.stats.errors
        self.tiles.checkpoint()
        flushed = writer.flush(FLUSH_TIMEOUT_S)
        known = self.tiled.known_tiles()
        for index in emptied:  # the flush may have written a snapshot taken before the drop
            if index not in known:  # not started again since (a new ISM there)
                store.remove(*index)
        return flushed and writer.stats.errors == errors
