"""Membership changes (:meth:`Handover._transition`): the tiles a member takes over are pulled
from a current owner and their journals replayed after the marks the copy holds; the tiles it no
longer owns are dropped from memory and from its own store.

On a *shared* store (an object store every member writes, :attr:`TileStore.shared`) tiles move
through the store: a member taking a tile over asks its owners to write their copy there
(``stored``: only the marks travel over Zenoh) and loads it; a tile no live member holds
(every owner gone, a whole cluster restarted on its bucket) is loaded as it is stored.  Either
way the journal is replayed after the loaded copy's marks.  A member that stops owning a tile
drops it from memory only, since the stored object is the cluster's.
"""

from __future__ import annotations

import logging
import time

import msgpack
import zenoh

from sogm_service.core.map.rendezvous import Ownership
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.exchange import TileExchange
from sogm_service.service.cluster.handover import replay_plan
from sogm_service.wire.tilefile import marks_of

log = logging.getLogger(__name__)


class Handover(TileExchange):
    """Pulling, installing and dropping tiles when the membership changes."""

    # -- membership changes ---------------------------------------------------------------
    def _transition(self, members: frozenset[str], joining: bool) -> None:
        started = time.perf_counter()
        self._busy = True
        view = Ownership(members, self.settings.replicas)
        with self._gate:
            prev = Ownership(frozenset(), self.settings.replicas) if joining else self._view
            assert prev is not None
            self._prev, self._view, self._installed = prev, view, set()
            for index in list(self._journal):
                if not self._pending(index):
                    del self._journal[index]
        log.info("cluster: members %s (was %s)", sorted(members), sorted(prev.members))
        held = self._held_elsewhere(settle=joining)
        local = self.tiled.known_tiles() | self._in_shared_store()
        candidates = {i for i in held | local | set(self._journal)
                      if view.owns(self.me, i) and not prev.owns(self.me, i)}
        pulled = 0
        for index in sorted(candidates):
            pulled += self._pull(index, index in held)
        with self._gate:  # tiles first written during the handover, or held by nobody
            leftover = [i for i in self._journal if self._pending(i)]
        for index in leftover:
            pulled += self._pull(index, True)
        with self._gate:
            self._prev, self._installed = None, set()
            self._journal.clear()
        dropped = self._drop_unowned(view)
        if not joining:  # a joiner's tiles came from the store or equal it
            self._write_new_primaries(prev, view)
        self.stats.count("cluster_transitions")
        self.stats.count("cluster_tiles_pulled", pulled)
        self.stats.count("cluster_tiles_dropped", dropped)
        self.stats.latency("cluster_transition", time.perf_counter() - started)
        log.info("cluster: transition done: %d tiles pulled, %d dropped, %d held",
                 pulled, dropped, len(self.tiled.known_tiles()))
        self._busy = False

    def _held_elsewhere(self, settle: bool) -> set[TileIndex]:
        """Every tile another member holds and serves (the union of their lists)."""
        assert self._session is not None
        held: set[TileIndex] = set()
        replies = self._session.get(
            self.keys.key("cluster", "held") + ("?settle=1" if settle else ""),
            target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
            allowed_destination=zenoh.Locality.REMOTE,
            timeout=self.settings.handover_timeout_s)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                got = msgpack.unpackb(reply.ok.payload.to_bytes())
                held.update((int(i), int(j)) for i, j in got["tiles"])
            except (ValueError, KeyError, TypeError, msgpack.UnpackException):
                self.stats.count("cluster_bad_replies")
        return held

    def _pull(self, index: TileIndex, ask: bool) -> int:
        """Bring ``index`` to its current state here and replay its journal; 1 if copied."""
        digest = self._local_digest(index)
        got = self._fetch_one(index, digest, self.settings.handover_timeout_s) if ask else None
        stored = self._load_shared(index) if got is None or got.status == "stored" else None
        if got is not None and got.status == "stored":
            if stored is None:  # written but unreadable here: replay the journal on ours
                log.error("cluster: tile %s was written to the shared store for us but could "
                          "not be loaded", index)
                self.stats.count("cluster_tiles_unavailable")
            got = None
        copied = 0
        with self._gate:
            applied: dict[str, Mark] = {}
            if stored is not None:  # the owner's copy, or the newest there is, from the store
                applied = stored
                self.stats.count("cluster_tiles_loaded_from_store")
            elif got is not None:
                applied = got.applied
                if got.status == "tile" and got.blob is not None:
                    copied = int(self._install(index, got.blob, applied))
                    if not copied:  # refused: our journal is replayed whole on ours
                        applied = {}
                elif got.status == "same":
                    resident = self.tiled.get_tile(index)
                    if resident is not None:
                        with resident.lock:
                            resident.applied = dict(applied)
                    self.stats.count("cluster_tiles_current")
                elif index in self.tiled.known_tiles():  # the owners have none: ours is stale
                    self.tiled.discard(index)
                    self._unstore(index)
            elif ask and self._view is not None and len(self._view.members) > 1:
                log.error("cluster: no owner of tile %s answered: its state before now is "
                          "lost here", index)
                self.stats.count("cluster_tiles_unavailable")
            journal = self._journal.pop(index, [])
            keep, skip = replay_plan(journal, applied)
            for job in keep:
                self.tiled.fuse(job.layer, job.increments, job.geometry, job.interp, job.stamp,
                                lambda i: i == index, (job.key, (job.stamp, job.digest)))
            if skip:
                self._skip[index] = skip
            else:
                self._skip.pop(index, None)
            self._installed.add(index)
        self.stats.count("cluster_isms_replayed", len(keep))
        return copied

    def _drop_unowned(self, view: Ownership) -> int:
        dropped = 0
        for index in sorted(self.tiled.known_tiles()):
            if not view.owns(self.me, index):
                self.tiled.discard(index)
                self._unstore(index)
                dropped += 1
        with self._gate:
            for index in list(self._skip):
                if not view.owns(self.me, index):
                    del self._skip[index]
        return dropped

    def _write_new_primaries(self, prev: Ownership, view: Ownership) -> None:
        """On a shared store, the tiles this member became primary of are written at the
        next checkpoint: their last primary may have left before writing them."""
        store = self.tiles.store
        if store is None or not store.shared:
            return
        for tile in self.tiled.resident():
            if view.primary(tile.index) == self.me and prev.primary(tile.index) != self.me:
                with tile.lock:
                    tile.saved_version = -1  # dirty: the next checkpoint writes it

    def _in_shared_store(self) -> set[TileIndex]:
        """Every tile of a shared store (listed now: other members write it too)."""
        store = self.tiles.store
        if store is None or not store.shared:
            return set()
        try:
            return set(store.index())
        except Exception as exc:
            log.error("cluster: could not list the shared store: %s", exc)
            return set()

    def _load_shared(self, index: TileIndex) -> dict[str, Mark] | None:
        """Tile ``index`` from a shared store into the map (its marks), or None when there is
        no shared store or no such tile there."""
        store = self.tiles.store
        if store is None or not store.shared:
            return None
        try:
            tile = store.load(*index)
        except Exception as exc:
            log.error("cluster: could not load tile %s from the shared store: %s", index, exc)
            return None
        if tile is None:
            return None
        h = tile.header
        applied = marks_of(h)
        with self._gate:
            self.tiled.insert_tile(index, list(h.layers), tile.data, h.stamp, saved=True,
                                   decay=dict(h.decay), applied=applied)
        return applied

    def _unstore(self, index: TileIndex) -> None:
        store = self.tiles.store
        if store is not None and not store.shared:  # a shared store's tile is the cluster's
            try:
                store.remove(*index)
            except OSError as exc:
                log.warning("cluster: could not remove tile %s from the store: %s", index, exc)
