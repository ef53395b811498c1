"""A cluster member's state and its view of tile ownership (:class:`ClusterView`): which tiles it
serves, owns or announces under the current membership, and which tiles of each ISM it fuses now
(:meth:`ClusterView.scope`; the others wait in a journal while a handover or reconciliation
brings them up to date).  The protocol is described in :mod:`sogm_service.service.cluster.cluster`.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from sogm_service.core.map.rendezvous import Ownership
from sogm_service.core.map.tile import Tile
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.replication import TileFiles
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.fusers import FuseJob, FuseWorkers
from sogm_service.service.server.stats import Stats
from sogm_service.wire.errors import ConfigError


class ClusterView:
    """This server's part of a map's cluster: its state, and the ownership it follows."""

    def __init__(self, config: ServiceConfig, tiled: TiledMap, tiles: Checkpointer,
                 stats: Stats, fusers: FuseWorkers,
                 settle: Callable[[float], bool]) -> None:
        """``settle(timeout)`` waits until this server has fused what it has received (a
        member answering a joiner's tile list first finishes its queue)."""
        self.config = config
        self.settings = config.cluster
        self.keys = config.keys
        self.tiled = tiled
        self.tiles = tiles
        self.stats = stats
        self.fusers = fusers
        self._settle = settle
        self.files = TileFiles.of(config.map)
        self.me = ""
        self._gate = threading.RLock()  # ingestion's scope vs installing a pulled tile
        self._view: Ownership | None = None
        self._prev: Ownership | None = None  # the view before the transition under way
        self._installed: set[TileIndex] = set()
        self._journal: dict[TileIndex, list[FuseJob]] = {}
        self._journaled = 0
        self._skip: dict[TileIndex, dict[str, Mark]] = {}
        # Reconciliation: tiles whose new ISMs are journaled meanwhile, ISMs on their way to
        # the fuse per tile, and the versions seen at the last round and last confirmed.
        self._reconciling: set[TileIndex] = set()
        self._inflight: dict[TileIndex, int] = {}
        self._flight = threading.Condition(self._gate)
        self._seen: dict[TileIndex, int] = {}
        self._checked: dict[TileIndex, int] = {}
        self._events: queue.Queue[tuple[str, str] | None] = queue.Queue()
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._thread: threading.Thread | None = None
        self._cache: dict[TileIndex, tuple[float, Tile | None]] = {}
        self._cache_lock = threading.Lock()
        self._stop = threading.Event()
        self._busy = True  # until the join is done
        fusers.scope = self.scope
        tiles.writes_tile = self.writes_tile
        if any(source.matching.mode != "off" for source in config.ism):
            raise ConfigError("scan matching reads the map, which a cluster member holds only "
                              "in part: turn [ism.matching] off with [cluster] enabled",
                              "cluster.enabled")

    # -- ownership ------------------------------------------------------------------------
    @property
    def view(self) -> Ownership | None:
        return self._view

    def _pending(self, index: TileIndex) -> bool:
        """Owned now, not before the transition under way, and not installed yet; or being
        reconciled with its primary."""
        if index in self._reconciling:
            return True
        prev = self._prev
        return prev is not None and index not in self._installed and \
            not prev.owns(self.me, index)

    def serves(self, index: TileIndex) -> bool:
        """This member owns ``index`` and holds its current state."""
        view = self._view
        return view is not None and view.owns(self.me, index) and not self._pending(index)

    def owns_none(self, box: tuple[int, int, int, int]) -> bool:
        """Whether this member owns (or is taking over) none of the tiles of ``box``
        (``i0, j0, i1, j1``, inclusive): an ISM there is other members' to fuse.  Before the
        first view, every tile may be ours."""
        view = self._view
        if view is None:
            return False
        i0, j0, i1, j1 = box
        return not any(view.owns(self.me, (i, j))
                       for j in range(j0, j1 + 1) for i in range(i0, i1 + 1))

    def writes_tile(self, index: TileIndex) -> bool:
        """Whether this member's checkpoints write ``index``: on a shared store its primary
        owner only (the replicas hold the same ISMs; one PUT per dirty tile, and no replica
        meets its co-owner's newer copy); with a store of its own, every owner.  Eviction
        writes whoever evicts."""
        store = self.tiles.store
        if store is None or not store.shared:
            return True
        view = self._view
        return view is None or view.primary(index) in (None, self.me)

    def announces(self, index: TileIndex) -> bool:
        """Whether this member publishes the tile events of ``index``: its primary owner
        only, so a fleet hears each tile switch once however many members track the robots
        (every member tracks them all).  Before the first view, every member does."""
        view = self._view
        return view is None or view.primary(index) in (None, self.me)

    def scope(self, job: FuseJob) -> frozenset[TileIndex]:
        """The tiles of ``job`` this member fuses now; pending ones keep the job in their
        journal (called by the fuse workers' ``submit``, in arrival order)."""
        indices = self.tiled.lattice.tiles_overlapping(job.geometry)
        out = []
        with self._gate:
            view = self._view
            for index in indices:
                if view is None:  # not joined yet: everything may be ours
                    self._keep(index, job)
                    continue
                if not view.owns(self.me, index):
                    continue
                if self._pending(index):
                    self._keep(index, job)
                    continue
                skip = self._skip.get(index)
                if skip is not None and job.key in skip:
                    mark = skip[job.key]
                    if (job.stamp, job.digest) == mark:
                        del skip[job.key]
                        continue
                    if job.stamp <= mark[0]:
                        continue  # the copy we pulled holds it already
                    del skip[job.key]
                out.append(index)
            for index in out:  # on their way to the fuse until the job is done
                self._inflight[index] = self._inflight.get(index, 0) + 1
        if out:
            report = job.done

            def done(touched: list[TileIndex], error: BaseException | None) -> None:
                self._landed(out)
                report(touched, error)
            job.done = done
        return frozenset(out)

    def _landed(self, indices: list[TileIndex]) -> None:
        with self._flight:
            for index in indices:
                left = self._inflight.get(index, 0) - 1
                if left > 0:
                    self._inflight[index] = left
                else:
                    self._inflight.pop(index, None)
            self._flight.notify_all()

    def _keep(self, index: TileIndex, job: FuseJob) -> None:
        kept = self._journal.setdefault(index, [])
        if len(kept) >= self.settings.journal_limit:
            kept.pop(0)
            self.stats.count("cluster_journal_dropped")
        kept.append(job)
        self._journaled += 1
