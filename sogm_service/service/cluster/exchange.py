"""Tiles between cluster members (``<prefix>/<map>/cluster/held`` and ``cluster/tile/<i>/<j>``):
asking the owners of a tile for it (every reply at once) and reading their answers
(:class:`Pulled`), installing a pulled copy, answering other members' tile lists and tile
requests, and fetching the tiles a window query needs from their owners.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.core.map.tile import Tile, TileSnapshot, planes_of
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.handover import content_digest
from sogm_service.service.cluster.view import ClusterView
from sogm_service.wire import encodings
from sogm_service.wire.errors import QueryError, TileFormatError
from sogm_service.wire.tilefile import TileHeader, tile_from_bytes

log = logging.getLogger(__name__)
MSGPACK = zenoh.Encoding(encodings.MSGPACK)  # a member's answers are msgpack maps

MAX_CLUSTER_BYTES = 64 << 20  # one cluster reply or request at most (a tile is ~N x 128 KiB)


@dataclass
class Pulled:
    """An owner's answer to a tile request: ``tile`` (with the blob), ``same`` (the asker's
    copy is current) or ``empty``, and the tile's applied marks."""

    status: str  # "tile" | "same" | "empty" | "stored" (written to the shared store: load it)
    applied: dict[str, Mark]
    blob: bytes | None = None


class TileExchange(ClusterView):
    """Asking for, installing, serving and fetching tiles."""

    # -- asking the owners ----------------------------------------------------------------
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
                   timeout: float) -> Pulled | None:
        replies = self._ask(index, digest, timeout, via_store=True)
        return self._first(replies)

    def _ask(self, index: TileIndex, digest: str | None, timeout: float,
             via_store: bool = False) -> Any:
        """``via_store``: on a shared store, the owner writes its copy there and answers
        ``stored`` instead of sending it (a handover loads it from the store)."""
        assert self._session is not None
        body = msgpack.packb({"digest": digest, "via_store": via_store})
        return self._session.get(self.keys.key("cluster", "tile", str(index[0]), str(index[1])),
                                 target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE,
                                 allowed_destination=zenoh.Locality.REMOTE,
                                 payload=body, timeout=timeout)

    def _first(self, replies: Iterable[zenoh.Reply], only: str | None = None) -> Pulled | None:
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
                return Pulled(str(got["status"]), applied, got.get("blob"))
            except (ValueError, KeyError, TypeError, IndexError, msgpack.UnpackException):
                self.stats.count("cluster_bad_replies")
        return None

    # -- answering other members ----------------------------------------------------------
    def served_tiles(self) -> list[TileIndex]:
        return sorted(i for i in self.tiled.known_tiles() if self.serves(i))

    def _on_held(self, q: zenoh.Query) -> None:
        try:
            params = dict(q.selector.parameters)  # type: ignore[call-overload]
            if params.get("settle"):
                self._settle(2.0)
            q.reply(q.key_expr, msgpack.packb({"member": self.me,
                                               "tiles": self.served_tiles()}),
                    encoding=MSGPACK)
        except Exception:
            log.exception("cluster: answering a tile list failed")

    def _on_tile(self, q: zenoh.Query) -> None:
        try:
            parts = str(q.key_expr).rsplit("/", 2)
            index = (int(parts[1]), int(parts[2]))
            if not self.serves(index):
                return  # not an owner, or not current yet: others answer
            digest, via_store = None, False
            if q.payload is not None:
                raw = q.payload.to_bytes()
                if len(raw) <= MAX_CLUSTER_BYTES:
                    body = msgpack.unpackb(raw)
                    if isinstance(body, dict):
                        digest, via_store = body.get("digest"), bool(body.get("via_store"))
            q.reply(q.key_expr, self.tile_answer(index, digest, via_store), encoding=MSGPACK)
            self.stats.count("cluster_tiles_served")
        except (ValueError, IndexError, TypeError, msgpack.UnpackException):
            self.stats.count("cluster_bad_requests")
        except Exception:
            log.exception("cluster: answering a tile failed")

    def tile_answer(self, index: TileIndex, digest: str | None,
                    via_store: bool = False) -> bytes:
        if index in self.tiled.known_tiles():
            self.tiled.get_tile(index)  # loads a stored tile
        snap = self.tiled.snapshot(index)
        if snap is None:
            return msgpack.packb({"status": "empty", "applied": []})
        applied = [[k, [v[0], v[1]]] for k, v in snap.applied.items()]
        if digest is not None and digest == content_digest(snap.layers, snap.data):
            return msgpack.packb({"status": "same", "applied": applied})
        if via_store and self._write_shared(snap):
            return msgpack.packb({"status": "stored", "applied": applied})
        return msgpack.packb({"status": "tile", "applied": applied,
                              "blob": self.files.encode(snap)})

    def _write_shared(self, snap: TileSnapshot) -> bool:
        """Write a snapshot to a shared store now (for a member taking the tile over to load
        it from there); False without a shared store or when the write fails."""
        store = self.tiles.store
        if store is None or not store.shared:
            return False
        try:
            store.write(snap.index[0], snap.index[1], snap.layers, snap.data, snap.stamp,
                        snap.decay or None, snap.applied or None, snap.version)
        except Exception as exc:
            log.warning("cluster: tile %s not written for a handover: %s", snap.index, exc)
            return False
        self.tiled.mark_saved(snap.index, snap.version)
        self.stats.count("cluster_tiles_written_for_handover")
        return True

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
        unanswered: list[TileIndex] = []
        for index, replies in asked:
            got = self._first(replies)
            tile = None
            if got is not None and got.status == "tile" and got.blob is not None:
                try:
                    stored = tile_from_bytes(got.blob, self.files.expect)
                    tile = self._as_tile(index, stored.header, stored.data)
                except TileFormatError as exc:
                    log.warning("cluster: tile %s came back damaged: %s", index, exc.reason)
                    got = None
            if got is None:
                unanswered.append(index)
                continue
            out[index] = tile
            self.stats.count("cluster_tiles_fetched")
        if unanswered:  # never a partial answer: the query fails, naming what it lacks
            self.stats.count("cluster_no_owner")
            named = ", ".join(str(i) for i in unanswered[:8])
            more = f" and {len(unanswered) - 8} more" if len(unanswered) > 8 else ""
            raise QueryError("no_owner", f"no owner of tile(s) {named}{more} answered within "
                                         f"{self.settings.fetch_timeout_s} s", "x")
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
