"""Where the map meets storage and the fleet (service layer, DESIGN.md section 3).

* **Tile store** (:mod:`sogm_service.store.format`): on start the store directory is indexed and
  every stored tile is known to the map (loaded on first touch).  Dirty tiles are checkpointed
  every ``checkpoint_interval_s``: a copy of the tile (the paper's double buffer) goes to the
  background :class:`~sogm_service.store.format.TileWriter`, so ingestion never waits for disk.
  A SIGKILL loses at most what changed since the last checkpoint; shutdown flushes everything.
* **Memory budget**: after each ISM and each checkpoint, least recently used tiles outside every
  robot's region of interest are evicted until the resident tiles fit the budget.  A dirty tile
  is snapshotted to the writer first; the writer's loader serves a snapshot still waiting for
  disk, so an evicted tile never comes back stale.
* **Tile manager** (:mod:`sogm_service.core.tilemanager`): follows robot poses (``pose/**``, or the
  centre of a robot's ISMs while it sends no poses), publishes tile-switch events on
  ``<prefix>/<map>/events/tile``, preloads tiles entering a region of interest and checkpoints
  those that left every region.  ``<prefix>/<map>/robots`` answers late joiners with each
  robot's current tile.
* **Replication**: ``<prefix>/<map>/tiles/<i>/<j>`` answers one tile in the store's file format;
  a get on ``tiles/**`` returns them all.  With ``tiles.replicate_on_start`` a server copies the
  map of a live peer before it starts answering.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.core.geometry import TileLattice
from sogm_service.core.tilemanager import TileManager, TileSwitchEvent
from sogm_service.core.tiles import TiledMap, TileIndex
from sogm_service.service.config import ServiceConfig
from sogm_service.service.stats import Stats
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.format import tile_from_bytes, tile_to_bytes
from sogm_service.store.writer import TileWriter
from sogm_service.wire import codec
from sogm_service.wire.errors import StoreLockedError, TileFormatError
from sogm_service.wire.messages import GeodeticFix, PoseModel, RobotTilesReply, TileEvent

log = logging.getLogger("sogm_service.service.persistence")

Guard = Callable[[str, Callable[[zenoh.Query], Any]], Callable[[zenoh.Query], None]]
LoaderResult = tuple[list[str], npt.NDArray[np.int16], float]


class Persistence:
    """Tile store, checkpoints, eviction, tile manager and replication of one map server."""

    def __init__(self, config: ServiceConfig, stats: Stats) -> None:
        self.config = config
        self.stats = stats
        self.lattice = TileLattice(config.map.resolution, config.map.tile_size)
        self.manager = TileManager(self.lattice, config.tiles.hysteresis_m,
                                   config.tiles.roi_radius_tiles, datum=config.map.datum,
                                   map_name=config.map.name)
        self.store: DirectoryStore | None = None
        self.writer: TileWriter | None = None
        self._map: TiledMap | None = None
        self._lock: threading.RLock | None = None
        self._manager_lock = threading.Lock()
        self._posed: set[str] = set()
        self._publisher: zenoh.Publisher | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._budget = int(config.storage.memory_budget_mb * 1e6)
        self._warned_budget = False
        # A read-only store object on no directory: builds headers and checks replicas.
        self._format = DirectoryStore(".", config.map.name, config.map.resolution,
                                 config.map.tile_size, frame=config.map.frame,
                                 datum=config.map.datum, readonly=True)

    # -- lifecycle ------------------------------------------------------------------------
    def open(self, tiled: TiledMap) -> None:
        """Open and index the store (fails fast if another server holds its directory)."""
        self._map = tiled
        directory = self.config.storage.directory
        if directory is None:
            return
        try:
            self.store = DirectoryStore(directory, self.config.map.name, self.config.map.resolution,
                                   self.config.map.tile_size, frame=self.config.map.frame,
                                   datum=self.config.map.datum)
        except StoreLockedError as exc:
            raise RuntimeError(
                f"tile store {directory} is in use by another server: {exc}") from None
        index = self.store.index()
        tiled.stored = set(index)
        for info in index.values():  # layers are known before any tile is loaded
            tiled.adopt_layers(info.header.layers)
        for problem in self.store.problems:
            self.stats.count("store_problems")
            log.warning("tile store: skipped %s: %s", problem.path, problem.reason)
        self.writer = TileWriter(self.store, on_saved=self._saved, on_error=self._failed)
        log.info("tile store %s: %d tiles indexed, %d skipped", directory, len(index),
                 len(self.store.problems))

    def load(self, i: int, j: int) -> LoaderResult | None:
        """The map's loader: a tile brought back from the writer queue or the store."""
        if self.writer is None:
            return None
        loaded = self.writer.loader(i, j)
        if loaded is not None:
            self.stats.count("tiles_loaded")
        return loaded

    def start(self, tiled: TiledMap, lock: threading.RLock) -> None:
        """Start the checkpoint thread (only with a store)."""
        self._map, self._lock = tiled, lock
        if self.writer is None:
            return
        self._thread = threading.Thread(target=self._checkpoint_loop, name="sogm-checkpoint",
                                        daemon=True)
        self._thread.start()

    def close(self, tiled: TiledMap, lock: threading.RLock, timeout: float) -> None:
        """Flush every dirty tile and stop background work."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        if self.writer is None or self.store is None:
            return
        self._lock = lock
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

    def checkpoint(self) -> int:
        """Snapshot every dirty tile to the writer; returns how many were submitted."""
        if self.writer is None or self._map is None or self._lock is None:
            return 0
        with self._lock:
            dirty = [t for t in self._map.tiles.values() if t.dirty]
            for tile in dirty:
                self._submit(tile.index)
        self.stats.count("checkpoints")
        return len(dirty)

    def _submit(self, index: TileIndex) -> None:
        """Copy one resident tile to the writer (caller holds the map lock)."""
        assert self.writer is not None and self._map is not None
        tile = self._map.tiles[index]
        names, data = self._map.tile_layers(tile)
        self.writer.submit(index[0], index[1], names, data.copy(), tile.stamp,
                           token=tile.version)

    def _saved(self, index: TileIndex, token: Any) -> None:
        if self._map is None or self._lock is None:
            return
        with self._lock:
            tile = self._map.tiles.get(index)
            if tile is not None and isinstance(token, int):
                tile.saved_version = max(tile.saved_version, token)
            self._map.stored.add(index)
        self.stats.count("tiles_written")

    def _failed(self, index: TileIndex, token: Any, exc: BaseException) -> None:
        self.stats.count("tile_write_errors")

    def enforce_budget(self) -> None:
        """Evict least recently used tiles outside every ROI until the budget holds."""
        if self._map is None or self._lock is None:
            return
        with self._lock:
            over = self._map.resident_bytes() - self._budget
            if over <= 0:
                return
            if self.writer is None:
                if not self._warned_budget:
                    log.warning("resident tiles exceed the memory budget and there is no "
                                "tile store to evict to; set storage.directory")
                    self._warned_budget = True
                return
            with self._manager_lock:
                keep = self.manager.regions_of_interest()
            for index in self._map.least_recently_used():
                if over <= 0:
                    break
                if index in keep:
                    continue
                if self._map.tiles[index].dirty:
                    self._submit(index)
                tile = self._map.evict(index)
                over -= tile.nbytes if tile is not None else 0
                self.stats.count("tiles_evicted")

    # -- robots ---------------------------------------------------------------------------
    def touched(self, tiles: list[TileIndex], robot: str | None,
                centre: tuple[float, float] | None = None, stamp: float = 0.0) -> None:
        """An ISM of ``robot`` centred at ``centre`` wrote ``tiles``."""
        if robot and centre is not None and robot not in self._posed:
            self._follow(robot, centre[0], centre[1], stamp)
        if tiles:
            self.enforce_budget()

    def robot_pose(self, robot: str, x: float, y: float, stamp: float) -> None:
        """A robot's pose from ``pose/**``: the tile manager follows it."""
        self._posed.add(robot)
        self._follow(robot, x, y, stamp)

    def _follow(self, robot: str, x: float, y: float, stamp: float) -> None:
        with self._manager_lock:
            event = self.manager.update(robot, x, y, stamp)
            entered, left = self.manager.roi_changes() if event else (set(), set())
        if event is None:
            return
        self.stats.count("tile_switches")
        self._publish(event)
        self._preload(entered)
        self._persist(left)

    def _publish(self, event: TileSwitchEvent) -> None:
        if self._publisher is not None:
            self._publisher.put(codec.encode(self.tile_event(event)))

    def tile_event(self, event: TileSwitchEvent) -> TileEvent:
        datum = None if event.datum is None else GeodeticFix(**event.datum.as_dict())
        return TileEvent(map=self.config.map.name, robot=event.robot, i=event.index[0],
                         j=event.index[1], name=event.name,
                         origin=PoseModel(x=event.origin.x, y=event.origin.y, yaw=0.0),
                         datum=datum, stamp=event.stamp)

    def _preload(self, tiles: set[TileIndex]) -> None:
        if self._map is None or self._lock is None or self.writer is None:
            return
        with self._lock:
            for index in tiles:
                if index not in self._map.tiles and index in self._map.stored:
                    self._map.get_tile(index)
                    self.stats.count("tiles_preloaded")

    def _persist(self, tiles: set[TileIndex]) -> None:
        if self._map is None or self._lock is None or self.writer is None:
            return
        with self._lock:
            for index in tiles:
                tile = self._map.tiles.get(index)
                if tile is not None and tile.dirty:
                    self._submit(index)

    # -- zenoh ----------------------------------------------------------------------------
    def declare(self, session: zenoh.Session, guard: Guard) -> list[Any]:
        """Declare the event publisher and the tile and robot queryables."""
        key = self.config.key
        self._publisher = session.declare_publisher(
            key("events", "tile"), congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE)
        return [
            self._publisher,
            session.declare_queryable(key("tiles", "**"), guard("tiles", self._on_tiles)),
            session.declare_queryable(key("robots"), guard("robots", self._on_robots)),
        ]

    def _on_robots(self, q: zenoh.Query) -> RobotTilesReply:
        with self._manager_lock:
            events = [self.tile_event(e) for e in self.manager.current_tiles().values()]
        return RobotTilesReply(map=self.config.map.name, robots=events)

    def _on_tiles(self, q: zenoh.Query) -> None:
        """One reply per requested tile, keyed ``.../tiles/<i>/<j>``, in the store format."""
        assert self._map is not None and self._lock is not None
        with self._lock:
            indices = sorted(self._map.known_tiles())
        selector = zenoh.KeyExpr(str(q.key_expr))
        for i, j in indices:
            tile_key = zenoh.KeyExpr(self.config.key("tiles", str(i), str(j)))
            if not selector.intersects(tile_key):
                continue
            blob = self.tile_bytes((i, j))
            if blob is not None:
                q.reply(tile_key, blob)
                self.stats.count("tiles_served")

    def tile_bytes(self, index: TileIndex) -> bytes | None:
        """A tile as file bytes: the live one if resident, else the stored file."""
        assert self._map is not None and self._lock is not None
        with self._lock:
            tile = self._map.tiles.get(index)
            if tile is not None:
                names, data = self._map.tile_layers(tile)
                data, stamp = data.copy(), tile.stamp
        if tile is None:
            return self.store.read_bytes(*index) if self.store is not None else None
        return tile_to_bytes(self._format.header_for(index[0], index[1], names, stamp), data)

    def replicate(self, session: zenoh.Session, timeout: float = 30.0) -> int:
        """Copy every tile a live server of this map offers on ``tiles/**``.

        Waits (up to ``timeout``) until another server of the map is visible by its liveliness
        token: right after the session opens, the connection to the peer may not be up yet,
        and a get then would find nothing and leave this server empty.
        """
        assert self._map is not None
        if not self._wait_for_peer(session, time.monotonic() + timeout):
            log.warning("replication: no live server of map %r within %.0f s; starting empty",
                        self.config.map.name, timeout)
            return 0
        expect = self._format.expect
        copied = 0
        for reply in session.get(self.config.key("tiles", "**"), timeout=timeout):
            if reply.ok is None:
                continue
            blob = reply.ok.payload.to_bytes()
            try:
                tile = tile_from_bytes(blob, expect)
            except TileFormatError as exc:
                self.stats.count("replica_tiles_rejected")
                log.warning("replication: rejected %s: %s", reply.ok.key_expr, exc.reason)
                continue
            h = tile.header
            self._map.insert_tile(h.index, list(h.layers), np.array(tile.data), h.stamp,
                                  saved=False)
            copied += 1
        self.stats.count("replica_tiles_copied", copied)
        log.info("replication: copied %d tiles from a live server", copied)
        return copied

    def _wait_for_peer(self, session: zenoh.Session, deadline: float) -> bool:
        key = self.config.key("@server", "*")
        while time.monotonic() < deadline:
            replies = session.liveliness().get(key, timeout=1.0)
            if any(r.ok is not None for r in replies):
                return True
            time.sleep(0.2)
        return False

    def stats_extra(self) -> dict[str, Any]:
        extra: dict[str, Any] = {"robots": len(self.manager.current_tiles())}
        if self._map is not None:
            extra["dirty_tiles"] = sum(1 for t in self._map.tiles.values() if t.dirty)
        if self.writer is not None:
            w = self.writer.stats
            extra.update(writes_pending=self.writer.pending(), tiles_written_total=w.written,
                         write_errors=w.errors, mb_written=round(w.bytes_written / 1e6, 3))
        return extra
