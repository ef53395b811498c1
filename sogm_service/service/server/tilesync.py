"""``<prefix>/<map>/tiles/changed``: the tiles of a region whose version differs from the one a
client holds, so an edge device keeps its neighbourhood without downloading it again.

A request (:class:`~sogm_service.wire.queries.TilesChangedRequest`, a msgpack body and/or
selector parameters) names the region, a box of the map frame or tile index bounds, and the
versions the client holds.  Admission prices it from those numbers alone
(:meth:`~sogm_service.service.server.admission.Admission.check_region`: the region's tiles and
the versions held, at most ``limits.max_region_tiles`` each) before any tile is read.  Then each
tile of the region that exists and whose version (``Tile.version``,
:mod:`sogm_service.core.map.tile`) differs from the one held, or that the client does not hold,
goes back as one reply keyed ``<prefix>/<map>/tiles/<i>/<j>`` in the store's tile format
(:mod:`sogm_service.wire.tilefile`, ``tile_version`` in its header), declared
``application/x-sogm-tile``; an unchanged tile costs nothing.  Tiles are never deleted, so a
tile the client holds always still exists.  Because the reply keys are not the query's, a get
must accept replies of any key (``accept_replies=zenoh.ReplyKeyExpr.ANY``); one that does not is
refused (``bad_parameter``) instead of failing inside Zenoh.

A resident tile is compared and sent from its snapshot; a tile that is only in the store by the
version its file's header has (read at the store's index, no file is opened for an unchanged
tile) and sent as the file's bytes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import zenoh

from sogm_service.core.map.tile import TileSnapshot
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.server.admission import Admission
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.queries import parse_request, selector
from sogm_service.service.server.stats import Stats
from sogm_service.wire import encodings
from sogm_service.wire.errors import QueryError
from sogm_service.wire.keys import MapKeys
from sogm_service.wire.queries import TilesChangedRequest

TILE = zenoh.Encoding(encodings.TILE)
_BYTES_PER_HELD = 32
"""Body bytes one held version may take (``"iiiii,jjjjj"`` and a 64-bit integer in msgpack are
about 20); a body beyond ``max_region_tiles`` of them is refused before it is unpacked."""


def parse_changed(params: Mapping[str, str], body: bytes | None,
                  max_tiles: int) -> TilesChangedRequest:
    """Selector parameters and an optional msgpack body -> the request (parameters win)."""
    if body and len(body) > _BYTES_PER_HELD * max_tiles + 1024:
        raise QueryError("window_too_large", f"the query body has {len(body)} bytes; at most "
                         f"{max_tiles} held versions are accepted", "held")
    return parse_request(TilesChangedRequest, params, body)


def held_versions(req: TilesChangedRequest) -> dict[TileIndex, int]:
    """The versions held, by tile index (``"i,j"`` keys or ``[i, j, version]`` triples)."""
    if isinstance(req.held, list):
        return {(i, j): v for i, j, v in req.held}
    out: dict[TileIndex, int] = {}
    for key, version in req.held.items():
        parts = key.split(",")
        try:
            if len(parts) != 2:
                raise ValueError(key)
            out[(int(parts[0]), int(parts[1]))] = version
        except ValueError:
            raise QueryError("bad_parameter", f"held key {key[:40]!r} is not \"i,j\"",
                             "held") from None
    return out


class TileSync:
    """Answers ``tiles/changed`` from this server's map and store."""

    def __init__(self, keys: MapKeys, tiled: TiledMap, checkpoints: Checkpointer,
                 encode: Callable[[TileSnapshot], bytes], admission: Admission,
                 stats: Stats) -> None:
        self.keys = keys
        self.tiled = tiled
        self.checkpoints = checkpoints
        self.encode = encode
        self.admission = admission
        self.stats = stats

    def on_changed(self, q: zenoh.Query) -> None:
        """One reply per changed tile of the region (module docstring)."""
        if str(q.key_expr) != self.keys.tiles_changed:
            return  # a wildcard get (``tiles/**``) asks for whole tiles, not for changes
        if q.accepts_replies() != zenoh.ReplyKeyExpr.ANY:
            raise QueryError("bad_parameter", "tiles/changed replies on the tiles' own keys: "
                             "ask with accept_replies=ReplyKeyExpr.ANY", "accept_replies")
        body = q.payload.to_bytes() if q.payload is not None else None
        pairs: list[tuple[str, str]] = list(q.selector.parameters)  # type: ignore[call-overload]
        params = selector(pairs)  # ``_anyke`` (Zenoh's own) left out; repeats refused
        req = parse_changed(params, body, self.admission.limits.max_region_tiles)
        held = held_versions(req)
        i0, j0, i1, j1 = self.admission.check_region(req, len(held))
        known = self.tiled.known_tiles()
        for index in sorted((t for t in known if i0 <= t[0] <= i1 and j0 <= t[1] <= j1),
                            key=lambda t: (t[1], t[0])):
            blob = self.changed_blob(index, held.get(index))
            if blob is None:
                self.stats.count("tiles_changed_unchanged")
                continue
            q.reply(zenoh.KeyExpr(self.keys.tile(*index)), blob, encoding=TILE)
            self.stats.count("tiles_changed_served")

    def changed_blob(self, index: TileIndex, held: int | None) -> bytes | None:
        """Tile ``index`` as tile bytes if its version is not ``held``, else None."""
        snap = self.tiled.snapshot(index)
        if snap is not None:
            return None if snap.version == held else self.encode(snap)
        store = self.checkpoints.store
        info = None if store is None else store.indexed().get(index)
        if store is None or info is None:
            return None
        if held and info.header.tile_version == held:
            return None
        return store.read_bytes(*index)
