"""Whole tiles over Zenoh: ``<prefix>/<map>/tiles/<i>/<j>`` and copying a live peer's map.

``tiles/<i>/<j>`` answers one tile in the store's file format (:mod:`sogm_service.store.format`);
a get on ``tiles/**`` returns them all.  With ``tiles.replicate_on_start`` a server copies the map
of a live peer of the same map before it starts answering anything.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import zenoh

from sogm_service.core.geodesy import LocalTangentPlane
from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.config import MapSettings, ServiceConfig
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.stats import Stats
from sogm_service.wire import encodings
from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.keys import tile_of_key
from sogm_service.wire.tilefile import (
    Expectation,
    marks_of,
    tile_from_bytes,
    tile_header,
    tile_to_bytes,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TileFiles:
    """This map's tiles in the store's file format, as replicas and cluster members send them
    to each other: stamp, datum, decay stamps and applied marks in the header."""

    expect: Expectation
    plane: LocalTangentPlane | None

    @classmethod
    def of(cls, m: MapSettings) -> TileFiles:
        return cls(Expectation(m.name, float(m.resolution), int(m.tile_size), m.frame),
                   None if m.datum is None else LocalTangentPlane(m.datum))

    def encode(self, snap: TileSnapshot) -> bytes:
        header = tile_header(self.expect, snap.index[0], snap.index[1], snap.layers, snap.stamp,
                             self.plane, snap.decay, snap.applied, snap.version)
        return tile_to_bytes(header, snap.data)

    def install(self, tiled: TiledMap, blob: bytes, index: TileIndex,
                applied: dict[str, Mark] | None = None) -> None:
        """Put a received tile in place of ours (not stored yet), with its own marks unless
        ``applied`` is given.  Raises ``TileFormatError`` for a damaged tile or another
        index than ``index``."""
        tile = tile_from_bytes(blob, self.expect)
        h = tile.header
        if h.index != index:
            raise TileFormatError(f"a reply for tile {index} holds tile {h.index}")
        tiled.insert_tile(index, list(h.layers), tile.data, h.stamp, saved=False,
                          decay=dict(h.decay), applied=marks_of(h) if applied is None else applied)


class Replication:
    """Serves this server's tiles and copies a peer's on start."""

    def __init__(self, config: ServiceConfig, tiled: TiledMap, tiles: Checkpointer,
                 stats: Stats) -> None:
        self.config = config
        self.keys = config.keys
        self.tiled = tiled
        self.tiles = tiles
        self.stats = stats
        self.files = TileFiles.of(config.map)

    def on_tiles(self, q: zenoh.Query) -> None:
        """One reply per requested tile, keyed ``.../tiles/<i>/<j>``, in the store format."""
        indices = sorted(self.tiled.known_tiles())
        selector = zenoh.KeyExpr(str(q.key_expr))
        for i, j in indices:
            tile_key = zenoh.KeyExpr(self.keys.tile(i, j))
            if not selector.intersects(tile_key):
                continue
            blob = self.tile_bytes((i, j))
            if blob is not None:
                q.reply(tile_key, blob, encoding=zenoh.Encoding(encodings.TILE))
                self.stats.count("tiles_served")

    def tile_bytes(self, index: TileIndex) -> bytes | None:
        """A tile as file bytes: the live one if resident, else the stored file."""
        snap = self.tiled.snapshot(index)
        if snap is None:
            store = self.tiles.store
            return store.read_bytes(*index) if store is not None else None
        return self.files.encode(snap)

    def replicate(self, session: zenoh.Session, timeout: float = 30.0) -> int:
        """Copy every tile a live server of this map offers on ``tiles/**``.

        Waits (up to ``timeout``) until another server of the map is visible by its liveliness
        token: right after the session opens, the connection to the peer may not be up yet,
        and a get then would find nothing and leave this server empty.
        """
        if not self._wait_for_peer(session, time.monotonic() + timeout):
            log.warning("replication: no live server of map %r within %.0f s; starting empty",
                        self.config.map.name, timeout)
            return 0
        copied = 0
        for reply in session.get(self.keys.all_tiles, timeout=timeout):
            if reply.ok is None:
                continue
            try:
                self.files.install(self.tiled, reply.ok.payload.to_bytes(),
                                   tile_of_key(str(reply.ok.key_expr)))
            except TileFormatError as exc:
                self.stats.count("replica_tiles_rejected")
                log.warning("replication: rejected %s: %s", reply.ok.key_expr, exc.reason)
                continue
            copied += 1
        self.stats.count("replica_tiles_copied", copied)
        log.info("replication: copied %d tiles from a live server", copied)
        return copied

    def _wait_for_peer(self, session: zenoh.Session, deadline: float) -> bool:
        while time.monotonic() < deadline:
            replies = session.liveliness().get(self.keys.all_servers, timeout=1.0)
            if any(r.ok is not None for r in replies):
                return True
            time.sleep(0.2)
        return False
