"""The map's tiles on disk: the store, checkpoints and the memory budget (architecture,
section 4: docs/architecture.md#4-maps-and-tiles).

* **Store**: on start the store directory is indexed and every stored tile is known to the map
  (loaded on first touch).  One server per directory: a second one fails fast.
* **Checkpoints** every ``checkpoint_interval_s``: a copy of each dirty tile (the paper's double
  buffer) goes to the background :class:`~sogm_service.store.writer.TileWriter`, so ingestion
  never waits for disk.  A SIGKILL loses at most what changed since the last checkpoint;
  shutdown flushes everything.
* **Memory budget**: after each ISM and each checkpoint, least recently used tiles outside every
  robot's region of interest are evicted until the resident tiles fit the budget.  A dirty tile
  is snapshotted to the writer first; the writer's loader serves a snapshot still waiting for
  disk, so an evicted tile never comes back stale.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from typing import Any

from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import LoaderResult, TileIndex
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.allocator import give_back
from sogm_service.service.server.stats import Stats
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.protocol import TileStore
from sogm_service.store.writer import TileWriter
from sogm_service.wire.errors import StoreConflictError, StoreLockedError

log = logging.getLogger(__name__)


def open_store(config: ServiceConfig) -> TileStore | None:
    """The configured tile store: a directory locked for this process, or an object store
    (``[store] url``) other servers may share; None without either."""
    if config.store.url is not None:
        from sogm_service.store.s3 import S3Store  # boto3 only when a site uses it

        return S3Store(config.store.url, config.map.name, config.map.resolution,
                       config.map.tile_size, frame=config.map.frame, datum=config.map.datum,
                       endpoint_url=config.store.endpoint_url)
    directory = config.storage.directory
    if directory is None:
        return None
    try:
        return DirectoryStore(directory, config.map.name, config.map.resolution,
                              config.map.tile_size, frame=config.map.frame,
                              datum=config.map.datum)
    except StoreLockedError as exc:
        raise StoreLockedError(f"tile store {directory} is in use by another server: {exc}",
                               str(directory), exc.pid) from None


class Checkpointer:
    """Store wiring, checkpoints and eviction of one map server's tiles."""

    def __init__(self, config: ServiceConfig, stats: Stats,
                 keep: Callable[[], set[TileIndex]]) -> None:
        """``keep`` names the tiles that must stay resident (every robot's region of interest)."""
        self.config = config
        self.stats = stats
        self._keep = keep
        self.store: TileStore | None = None
        self.writer: TileWriter | None = None
        self._tiled: TiledMap | None = None
        # Which dirty tiles a checkpoint writes (None: all).  A cluster on a shared store
        # leaves each tile to its primary owner, whose copy holds what its replicas hold.
        self.writes_tile: Callable[[TileIndex], bool] | None = None
        self._budget = int(config.storage.memory_budget_mb * 1e6)
        self._writer_bound = int(config.limits.max_writer_queue_mb * 1e6)
        self._warned_budget = False
        self._evicting = threading.Lock()
        self._evicted_at_trim = 0  # tiles_evicted when memory was last given back
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------
    def attach(self, tiled: TiledMap) -> None:
        """Open the store (failing fast if another server holds it), index it into the map
        (not serving yet) and start the writer."""
        self._tiled = tiled
        self.store = open_store(self.config)
        if self.store is None:
            return
        index = self.store.index()
        tiled.stored = set(index)
        for info in index.values():  # layers are known before any tile is loaded
            tiled.adopt_layers(info.header.layers)
            tiled.advance_clock(info.header.stamp)  # decaying layers read at the map's time
        for problem in self.store.problems:
            self.stats.count("store_problems")
            log.warning("tile store: skipped %s: %s", problem.path, problem.reason)
        self.writer = TileWriter(self.store, on_saved=self._saved, on_error=self._failed)
        log.info("tile store %s: %d tiles indexed, %d skipped",
                 self.config.store.url or self.config.storage.directory,
                 len(index), len(self.store.problems))

    def load(self, i: int, j: int) -> LoaderResult | None:
        """The map's loader: a tile brought back from the writer queue or the store."""
        if self.writer is None:
            return None
        loaded = self.writer.loader(i, j)
        if loaded is not None:
            self.stats.count("tiles_loaded")
        return loaded

    def start(self) -> None:
        """Start the checkpoint thread (only with a store)."""
        if self.writer is None:
            return
        self._thread = threading.Thread(target=self._checkpoint_loop, name="sogm-checkpoint",
                                        daemon=True)
        self._thread.start()

    def close(self, timeout: float) -> None:
        """Flush every dirty tile and stop background work."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        if self.writer is None or self.store is None:
            return
        self.checkpoint()
        if not self.writer.close(timeout):
            log.error("tile writer did not finish within %.1f s", timeout)
        self.store.close()
        log.info("tile store flushed: %d tiles written in total", self.writer.stats.written)

    # -- checkpoints and eviction ---------------------------------------------------------
    def _checkpoint_loop(self) -> None:
        while not self._stop.wait(self.config.storage.checkpoint_interval_s):
            self.checkpoint()
            self.enforce_budget()
            self.give_back_memory()

    def give_back_memory(self) -> bool:
        """Once tiles were evicted and every snapshot is written, hand the freed pages back to
        the OS (:func:`~sogm_service.service.server.allocator.give_back`): the planes of evicted
        tiles lie between live heap blocks, which no automatic trim returns.  At most once a
        checkpoint interval, and only after evictions; True when pages went back."""
        evicted = self.stats.snapshot()[0].get("tiles_evicted", 0)
        if evicted == self._evicted_at_trim or self.writer is None or self.writer.pending():
            return False
        self._evicted_at_trim = evicted
        released = give_back()
        self.stats.count("memory_given_back" if released else "memory_give_back_none")
        return released

    def checkpoint(self) -> int:
        """Snapshot every dirty tile to the writer; returns how many were submitted."""
        if self.writer is None or self._tiled is None:
            return 0
        n = self._submit_dirty(t.index for t in self._tiled.resident() if t.dirty)
        self.stats.count("checkpoints")
        return n

    def persist(self, indices: Iterable[TileIndex]) -> None:
        """Snapshot these tiles now if they are resident and dirty (they left every ROI)."""
        if self.writer is not None:
            self._submit_dirty(indices)

    def preload(self, indices: Iterable[TileIndex]) -> None:
        """Bring stored tiles back into memory before a robot needs them."""
        if self.writer is None or self._tiled is None:
            return
        for index in indices:
            if index not in self._tiled.tiles and index in self._tiled.stored:
                self._tiled.get_tile(index)
                self.stats.count("tiles_preloaded")

    def _submit_dirty(self, indices: Iterable[TileIndex]) -> int:
        assert self._tiled is not None
        n = 0
        for index in indices:
            snap = self._tiled.snapshot(index)
            if snap is None or not snap.dirty:
                continue
            if self.writes_tile is not None and not self.writes_tile(index):
                self._tiled.mark_saved(index, snap.version)  # another server writes it
                self.stats.count("tiles_left_to_primary")
                continue
            self._submit(snap)
            n += 1
        return n

    def _submit(self, snap: TileSnapshot) -> None:
        """A tile's snapshot (already a copy: the paper's double buffer) to the writer."""
        assert self.writer is not None
        self.writer.submit(snap.index[0], snap.index[1], snap.layers, snap.data, snap.stamp,
                           token=snap.version, decay=snap.decay, applied=snap.applied)

    def _saved(self, index: TileIndex, token: Any) -> None:
        if self._tiled is not None and isinstance(token, int):
            self._tiled.mark_saved(index, token)
        self.stats.count("tiles_written")

    def _failed(self, index: TileIndex, token: Any, exc: BaseException) -> None:
        self.stats.count("tile_write_errors")
        if isinstance(exc, StoreConflictError):  # a shared store holds a newer copy
            self.stats.count("store_writes_fenced")

    def writer_full(self) -> bool:
        """The store's writer holds ``max_writer_queue_mb`` of snapshots or more."""
        return self.writer is not None and self.writer.pending_bytes() >= self._writer_bound

    def enforce_budget(self) -> None:
        """Evict least recently used tiles outside every ROI until the budget holds (one
        eviction pass at a time; a caller that finds one running leaves it the work)."""
        if self._tiled is None or not self._evicting.acquire(blocking=False):
            return
        try:
            self._evict_over_budget(self._tiled)
        finally:
            self._evicting.release()

    def _evict_over_budget(self, tiled: TiledMap) -> None:
        over = tiled.resident_bytes() - self._budget
        if over <= 0:
            return
        if self.writer is None:
            if not self._warned_budget:
                log.warning("resident tiles exceed the memory budget and there is no "
                            "tile store to evict to; set storage.directory")
                self._warned_budget = True
            return
        keep = self._keep()
        for index in tiled.least_recently_used():
            if over <= 0:
                break
            resident = tiled.tiles.get(index)
            if index in keep or resident is None:
                continue
            if resident.dirty and self.writer_full():
                # Its copy would only pile up behind the disk: leave it resident; admission
                # refuses new tiles meanwhile (memory_budget), so memory stays bounded.
                self.stats.count("evictions_deferred_writer_full")
                continue
            tile = tiled.evict(index, before=self._submit_if_dirty)
            if tile is not None:  # None: gone meanwhile, or pinned by a fuse in progress
                over -= tile.nbytes
                self.stats.count("tiles_evicted")

    def _submit_if_dirty(self, snap: TileSnapshot) -> None:
        if snap.dirty:
            self._submit(snap)

    def stats_extra(self) -> dict[str, Any]:
        extra: dict[str, Any] = {}
        if self._tiled is not None:
            extra["dirty_tiles"] = sum(1 for t in self._tiled.resident() if t.dirty)
        if self.writer is not None:
            w = self.writer.stats
            extra.update(writes_pending=self.writer.pending(),
                         writes_pending_mb=round(self.writer.pending_bytes() / 1e6, 3),
                         tiles_written_total=w.written,
                         write_errors=w.errors, mb_written=round(w.bytes_written / 1e6, 3))
        return extra
