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

Scan matching (which reads the map) is not supported in a cluster.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.core.map.rendezvous import Ownership
from sogm_service.core.map.tile import Tile, planes_of
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.gathered import GatheredMap
from sogm_service.service.cluster.handover import content_digest, replay_plan
from sogm_service.service.cluster.replication import TileFiles
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.fusers import FuseJob, FuseWorkers
from sogm_service.service.server.stats import Stats
from sogm_service.store.format import (
    TileHeader,
    tile_from_bytes,
)
from sogm_service.wire.errors import ConfigError, QueryError, TileFormatError
from sogm_service.wire.keys import last_chunk

log = logging.getLogger(__name__)

_MAX_CLUSTER_BYTES = 64 << 20  # one cluster reply or request at most (a tile is ~N x 128 KiB)


@dataclass
class _Pulled:
    status: str  # "tile" | "same" | "empty"
    applied: dict[str, Mark]
    blob: bytes | None = None


class Cluster:
    """This server's part of a map's cluster (module docstring)."""

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
        self._idle = threading.Condition()
        self._busy = True  # until the join is done
        fusers.scope = self.scope
        if any(source.matching.mode != "off" for source in config.ism):
            raise ConfigError("scan matching reads the map, which a cluster member holds only "
                              "in part: turn [ism.matching] off with [cluster] enabled",
                              "cluster.enabled")

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

    def wait_stable(self, timeout: float) -> bool:
        """Block until no handover is under way (tests, bench)."""
        with self._idle:
            return self._idle.wait_for(lambda: not self._busy and self._events.empty(),
                                       timeout)

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

    # -- membership changes ---------------------------------------------------------------
    def _transition(self, members: frozenset[str], joining: bool) -> None:
        started = time.perf_counter()
        with self._idle:
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
        local = self.tiled.known_tiles()
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
        self.stats.count("cluster_transitions")
        self.stats.count("cluster_tiles_pulled", pulled)
        self.stats.count("cluster_tiles_dropped", dropped)
        self.stats.latency("cluster_transition", time.perf_counter() - started)
        log.info("cluster: transition done: %d tiles pulled, %d dropped, %d held",
                 pulled, dropped, len(self.tiled.known_tiles()))
        with self._idle:
            self._busy = False
            self._idle.notify_all()

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
        copied = 0
        with self._gate:
            applied: dict[str, Mark] = {}
            if got is not None:
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

    # -- reconciliation with the primary (module docstring) ---------------------------------
    def _reconcile_round(self) -> None:
        view = self._view
        if view is None or self._busy or self.settings.replicas < 2 or len(view.members) < 2:
            return
        for tile in self.tiled.resident():
            index = tile.index
            if self._stop.is_set() or not self._events.empty():
                return  # a membership change first
            version, seen = tile.version, self._seen.get(index)
            self._seen[index] = version
            if version != seen or version == self._checked.get(index):
                continue  # still changing, or confirmed since its last change
            primary = view.primary(index)
            if primary is None or primary == self.me or not view.owns(self.me, index):
                continue
            try:
                self._reconcile(index, primary)
            except Exception:
                log.exception("cluster: reconciling tile %s failed", index)
        for index in list(self._seen):
            if index not in self.tiled.tiles:
                self._seen.pop(index, None)
                self._checked.pop(index, None)

    def _reconcile(self, index: TileIndex, primary: str) -> None:
        """Compare tile ``index`` with its primary's copy and adopt that when they differ."""
        with self._gate:
            self._reconciling.add(index)  # from now on its ISMs wait in the journal
        got: _Pulled | None = None
        try:
            with self._flight:
                landed = self._flight.wait_for(lambda: not self._inflight.get(index),
                                               self.settings.handover_timeout_s)
            if not landed:
                self.stats.count("cluster_reconcile_deferred")
                return
            digest = self._local_digest(index)
            got = self._first(self._ask(index, digest, self.settings.handover_timeout_s),
                              only=primary)
            self.stats.count("cluster_reconcile_checked")
        finally:
            self._finish_reconcile(index, got)

    def _finish_reconcile(self, index: TileIndex, got: _Pulled | None) -> None:
        """Install the primary's copy (if it differs) and fuse what was journaled meanwhile."""
        with self._gate:
            applied: dict[str, Mark] = {}
            if got is not None and got.status == "tile" and got.blob is not None and \
                    self._install(index, got.blob, got.applied):
                applied = got.applied
                self.stats.count("cluster_tiles_reconciled")
            keep, skip = replay_plan(self._journal.pop(index, []), applied)
            for job in keep:
                self.tiled.fuse(job.layer, job.increments, job.geometry, job.interp, job.stamp,
                                lambda i: i == index, (job.key, (job.stamp, job.digest)))
            if skip:
                self._skip[index] = skip
            self._reconciling.discard(index)
            current = self.tiled.tiles.get(index)
            if current is not None and got is not None and got.status in ("same", "tile"):
                self._checked[index] = self._seen[index] = current.version

    def _install(self, index: TileIndex, blob: bytes, applied: dict[str, Mark]) -> bool:
        """A pulled copy in place of ours; a damaged one is counted and ours kept (the
        journal is replayed either way)."""
        try:
            self.files.install(self.tiled, blob, index, applied)
        except TileFormatError as exc:
            self.stats.count("cluster_bad_replies")
            log.warning("cluster: a copy of tile %s was refused: %s", index, exc.reason)
            return False
        return True

    def _local_digest(self, index: TileIndex) -> str | None:
        if index not in self.tiled.known_tiles():
            return None
        self.tiled.get_tile(index)  # a stored tile comes back to be compared
        snap = self.tiled.snapshot(index)
        return None if snap is None else content_digest(snap.layers, snap.data)

    def _fetch_one(self, index: TileIndex, digest: str | None,
                   timeout: float) -> _Pulled | None:
        replies = self._ask(index, digest, timeout)
        return self._first(replies)

    def _ask(self, index: TileIndex, digest: str | None, timeout: float) -> Any:
        assert self._session is not None
        body = msgpack.packb({"digest": digest})
        return self._session.get(self.keys.key("cluster", "tile", str(index[0]), str(index[1])),
                                 target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE,
                                 allowed_destination=zenoh.Locality.REMOTE,
                                 payload=body, timeout=timeout)

    def _first(self, replies: Iterable[zenoh.Reply], only: str | None = None) -> _Pulled | None:
        """The first valid owner's answer (every owner holds the same state), or ``only``'s."""
        for reply in replies:
            if reply.ok is None:
                continue
            if only is not None and (reply.replier_id is None
                                     or str(reply.replier_id.zid) != only):
                continue
            try:
                got = msgpack.unpackb(reply.ok.payload.to_bytes())
                applied = {str(k): (float(v[0]), int(v[1])) for k, v in got["applied"]}
                return _Pulled(str(got["status"]), applied, got.get("blob"))
            except (ValueError, KeyError, TypeError, IndexError, msgpack.UnpackException):
                self.stats.count("cluster_bad_replies")
        return None

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

    def _unstore(self, index: TileIndex) -> None:
        store = self.tiles.store
        if store is not None:
            try:
                store.remove(*index)
            except OSError as exc:
                log.warning("cluster: could not remove tile %s from the store: %s", index, exc)

    # -- answering other members ----------------------------------------------------------
    def served_tiles(self) -> list[TileIndex]:
        return sorted(i for i in self.tiled.known_tiles() if self.serves(i))

    def _on_held(self, q: zenoh.Query) -> None:
        try:
            params = dict(q.selector.parameters)  # type: ignore[call-overload]
            if params.get("settle"):
                self._settle(2.0)
            q.reply(q.key_expr, msgpack.packb({"member": self.me,
                                               "tiles": self.served_tiles()}))
        except Exception:
            log.exception("cluster: answering a tile list failed")

    def _on_tile(self, q: zenoh.Query) -> None:
        try:
            parts = str(q.key_expr).rsplit("/", 2)
            index = (int(parts[1]), int(parts[2]))
            if not self.serves(index):
                return  # not an owner, or not current yet: others answer
            digest = None
            if q.payload is not None:
                raw = q.payload.to_bytes()
                if len(raw) <= _MAX_CLUSTER_BYTES:
                    body = msgpack.unpackb(raw)
                    if isinstance(body, dict):
                        digest = body.get("digest")
            q.reply(q.key_expr, self.tile_answer(index, digest))
            self.stats.count("cluster_tiles_served")
        except (ValueError, IndexError, TypeError, msgpack.UnpackException):
            self.stats.count("cluster_bad_requests")
        except Exception:
            log.exception("cluster: answering a tile failed")

    def tile_answer(self, index: TileIndex, digest: str | None) -> bytes:
        if index in self.tiled.known_tiles():
            self.tiled.get_tile(index)  # loads a stored tile
        snap = self.tiled.snapshot(index)
        if snap is None:
            return msgpack.packb({"status": "empty", "applied": []})
        applied = [[k, [v[0], v[1]]] for k, v in snap.applied.items()]
        if digest is not None and digest == content_digest(snap.layers, snap.data):
            return msgpack.packb({"status": "same", "applied": applied})
        return msgpack.packb({"status": "tile", "applied": applied,
                              "blob": self.files.encode(snap)})

    # -- queries: gathering tiles from owners ---------------------------------------------
    def fetch(self, indices: list[TileIndex]) -> dict[TileIndex, Tile | None]:
        """The tiles this member cannot serve, from their owners (None: the owner has none).
        Raises ``QueryError('no_owner')`` when no owner of one of them answers in time."""
        out: dict[TileIndex, Tile | None] = {}
        now = time.monotonic()
        missing = []
        with self._cache_lock:
            for index in indices:
                hit = self._cache.get(index)
                if hit is not None and hit[0] > now:
                    out[index] = hit[1]
                    self.stats.count("cluster_cache_hits")
                else:
                    missing.append(index)
        asked = [(index, self._ask(index, None, self.settings.fetch_timeout_s))
                 for index in missing]
        for index, replies in asked:
            got = self._first(replies)
            if got is None:
                self.stats.count("cluster_no_owner")
                raise QueryError("no_owner", f"no owner of tile {index} answered within "
                                             f"{self.settings.fetch_timeout_s} s", "x")
            tile = None
            if got.status == "tile" and got.blob is not None:
                try:
                    stored = tile_from_bytes(got.blob, self.files.expect)
                except TileFormatError as exc:
                    raise QueryError("no_owner", f"tile {index} came back damaged: "
                                                 f"{exc.reason}", "x") from None
                tile = self._as_tile(index, stored.header, stored.data)
            out[index] = tile
            self.stats.count("cluster_tiles_fetched")
        if self.settings.fetch_cache_s > 0 and self.settings.fetch_cache_tiles > 0 and missing:
            until = time.monotonic() + self.settings.fetch_cache_s
            with self._cache_lock:
                for index in missing:
                    self._cache[index] = (until, out[index])
                while len(self._cache) > self.settings.fetch_cache_tiles:
                    self._cache.pop(next(iter(self._cache)))
        return out

    def _as_tile(self, index: TileIndex, header: TileHeader,
                 stack: npt.NDArray[np.int16]) -> Tile:
        """A fetched tile in this map's layer order (read-only use), with its stamp and decay
        stamps: a decaying layer reads as decayed to the query's time, as the owner's does."""
        ids = self.tiled.adopt_layers(list(header.layers))
        by_name = dict(zip(header.layers, ids, strict=True))
        return Tile(index, planes_of(ids, stack), stamp=header.stamp,
                    decay={by_name[name]: t for name, t in header.decay})

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
