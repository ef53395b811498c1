"""One map over several servers: membership, tile ownership, handover and gathering.

Architecture, section 10: docs/architecture.md#10-several-servers-one-map.  With
``[cluster] enabled = true`` the servers of one map form a
cluster without a coordinator:

* **Membership**: the servers' liveliness tokens ``<prefix>/<map>/@server/<id>``.  A DELETE of a
  token (a server stopped, crashed or got cut off) removes the member.
* **Ownership**: every tile has ``replicas`` owners, the members ranking first for it by
  rendezvous hashing (:mod:`sogm_service.core.map.rendezvous`).  Every member computes the same
  owners from the same membership.
* **Ingestion**: every member receives every ISM and fuses only the tiles it owns (primary or
  replica), in arrival order: :meth:`Cluster.scope` gives each ISM's fuse job the set of its
  tiles this member may write (:class:`~sogm_service.service.server.fusers.FuseWorkers` combines it
  with the fuse workers' own shares).  Each tile records, per ISM key, the last ISM fused into
  it (stamp and a digest of the payload: ``Tile.applied``, stored with the tile).
* **Handover**: when the membership changes from ``prev`` to ``view``, the tiles this member
  owns under ``view`` and did not own under ``prev`` are *pending*: ISMs touching them are
  kept in a journal instead of being fused.  Each is pulled from a member that owns it and is
  not pending itself (``cluster/tile/<i>/<j>``, every reply at once: consolidation NONE), with
  its ``applied`` marks; then the journal is replayed from just after the last ISM the copy
  already holds, per ISM key, so an ISM is neither lost nor fused twice.  A joining member
  does all this *before* it declares its token (so nobody relies on it yet); a member whose
  stored copy is current (same content digest) receives only the marks (restart without a
  full copy).  When a member leaves, the survivors that now own its tiles pull them from the
  remaining replicas.  Tiles a member no longer owns are dropped (memory and store).
* **Queries**: any member answers any window query: tiles it cannot serve itself are fetched
  from their owners (:class:`GatheredMap`), within ``fetch_timeout_s``; when no owner of a
  needed tile answers, the query is refused with ``no_owner``.  Fetched tiles are kept
  ``fetch_cache_s`` (read-only, never fused, never stored).

* **Reconciliation**: replicas hold the same bytes when every member sees the ISMs that touch
  a tile in the same order, which Zenoh guarantees per publisher only; two publishers writing
  one tile at the same moment may reach two members in different orders, and Eq. 1 with its
  clamp is order-independent only until a cell saturates (a lost message, or members with
  different ISM sources, diverge too).  So every ``reconcile_interval_s`` a replica takes each
  tile that changed since its last check and then stayed quiet for a whole interval, holds
  back new ISMs for it (journal), waits for those already on their way to be fused, and asks
  its primary with its content digest: ``same``, or the primary's copy, which it installs
  before replaying the journal as a handover does.  The primary's copy wins.

* **A shared store** (``[store] url``: one bucket for every member): a member taking a tile
  over asks its owners to write their copy there (answer ``stored``) and loads it; a tile no
  live member holds is loaded as stored; checkpoints write a tile on its primary only, and a
  member never deletes a tile it stopped owning from the bucket.  Writes are fenced
  (:mod:`sogm_service.store.s3`), so a member back from a pause cannot overwrite newer tiles.

Scan matching (which reads the map) is not supported in a cluster.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import zenoh

from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.cluster.gathered import GatheredMap
from sogm_service.service.cluster.reconcile import Reconciliation
from sogm_service.service.cluster.transition import Handover
from sogm_service.wire.keys import last_chunk

log = logging.getLogger(__name__)


class Cluster(Handover, Reconciliation):
    """This server's part of a map's cluster (module docstring): the ownership view
    (:class:`~sogm_service.service.cluster.view.ClusterView`), the tile exchange with other
    members (:class:`~sogm_service.service.cluster.exchange.TileExchange`), handovers
    (:class:`~sogm_service.service.cluster.transition.Handover`) and reconciliation
    (:class:`~sogm_service.service.cluster.reconcile.Reconciliation`), started and stopped
    here with the membership it follows."""

    # -- lifecycle ------------------------------------------------------------------------
    def join(self, session: zenoh.Session, me: str) -> None:
        """Find the members, pull the tiles this server will own and start following the
        membership.  Call after the ISM subscribers and before the server's token."""
        self._session, self.me = session, me
        s = session
        self._declared.append(s.declare_queryable(self.keys.key("cluster", "held"),
                                                  self._on_held))
        self._declared.append(s.declare_queryable(self.keys.key("cluster", "tile", "**"),
                                                  self._on_tile))
        self._declared.append(s.liveliness().declare_subscriber(
            self.keys.all_servers, self._on_token, history=True))
        members = self._live_members() | {me}
        log.info("cluster: joining map %r with %d member(s), %d replicas", self.config.map.name,
                 len(members) - 1, self.settings.replicas)
        self._transition(frozenset(members), joining=True)
        self._thread = threading.Thread(target=self._follow, name="sogm-cluster", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._events.put(None)
        if self._thread is not None:
            self._thread.join(5.0)
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)
        self._declared.clear()

    def _live_members(self) -> set[str]:
        assert self._session is not None
        found = set()
        for reply in self._session.liveliness().get(self.keys.all_servers, timeout=2.0):
            if reply.ok is not None:
                found.add(last_chunk(str(reply.ok.key_expr)))
        return found

    def _on_token(self, sample: zenoh.Sample) -> None:
        kind = "delete" if sample.kind == zenoh.SampleKind.DELETE else "put"
        self._events.put((kind, last_chunk(str(sample.key_expr))))

    def _follow(self) -> None:
        """Apply membership changes one transition at a time (batched over ``settle_s``)."""
        every = self.settings.reconcile_interval_s or None
        while not self._stop.is_set():
            try:
                event = self._events.get(timeout=every)
            except queue.Empty:  # a quiet interval: membership first, then replicas
                self._reconcile_round()
                continue
            if event is None:
                return
            events = [event]
            deadline = time.monotonic() + self.settings.settle_s
            while (left := deadline - time.monotonic()) > 0:
                try:
                    more = self._events.get(timeout=left)
                except queue.Empty:
                    break
                if more is None:
                    return
                events.append(more)
            assert self._view is not None
            members = set(self._view.members)
            for kind, member in events:
                if member == self.me:
                    continue
                if kind == "put":
                    members.add(member)
                else:
                    members.discard(member)
            if frozenset(members) != self._view.members:
                try:
                    self._transition(frozenset(members), joining=False)
                except Exception:
                    log.exception("cluster: membership change failed")

    # -- the map queries read ---------------------------------------------------------------
    def query_map(self) -> TiledMap:
        """The map a window query reads: this member's tiles and its owners' for the rest."""
        return GatheredMap(self.tiled, self)

    def all_tiles(self) -> set[TileIndex]:
        """Every tile of the cluster's map (this member's and every other member's list)."""
        return self.tiled.known_tiles() | self._held_elsewhere(settle=False)

    def stats_extra(self) -> dict[str, Any]:
        view = self._view
        held = self.tiled.known_tiles()
        primary = sum(1 for i in held if view is not None and view.primary(i) == self.me)
        return {"cluster_members": sorted(view.members) if view is not None else [],
                "cluster_replicas": self.settings.replicas,
                "cluster_tiles_held": len(held),
                "cluster_tiles_primary": primary,
                "cluster_tiles_replica": len(held) - primary,
                "cluster_handover": self._busy}
