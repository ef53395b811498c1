"""A local copy of a region's tiles, kept up to date by pulling only what changed
(:meth:`MapClient.mirror <sogm_service.client.mapclient.MapClient.mirror>`).

>>> mirror = client.mirror(x=0.0, y=0.0, width=40.0, height=40.0)
>>> mirror.refresh()                   # the first pulls every tile of the region
>>> mirror.refresh()                   # later ones only the tiles whose version moved
>>> logodds, geometry = mirror.layer("obstacle")

The region is the tiles a box of the map frame overlaps (centre ``x``, ``y``, ``width`` and
``height`` in m), fixed when the mirror is made, and asked as tile index bounds.  Each
:meth:`TileMirror.refresh` sends ``sogm/<map>/tiles/changed`` the versions held; the server
answers each tile whose version differs as the store's tile bytes, decoded here with the
store's own reader (:mod:`sogm_service.wire.tilefile`: checksums, shape, value range).  The
planes are the server's, bit for bit: int16 log-odds in 1/1000 nat
(:mod:`sogm_service.core.logodds`), an absent plane all unknown (0).  A decaying layer is held as
the server holds it (its cells and decay stamp); :meth:`TileMirror.layer` reads it as at a time
given, with the layer's half-life, by the map's own decay rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import zenoh

from sogm_service.client.results import service_error
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.map import forget
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.wire import codec
from sogm_service.wire.errors import QueryTimeoutError
from sogm_service.wire.keys import MapKeys, tile_of_key
from sogm_service.wire.queries import InfoReply, TilesChangedRequest
from sogm_service.wire.tilefile import Expectation, tile_from_bytes

Fixed = npt.NDArray[np.int16]


@dataclass
class HeldTile:
    """One tile as the mirror holds it: its version and planes, where it lies."""

    index: TileIndex
    version: int
    planes: dict[str, Fixed]
    stamp: float
    geometry: GridGeometry
    decay: dict[str, float] = field(default_factory=dict)

    def plane(self, layer: str) -> Fixed:
        """The ``(T, T)`` log-odds of ``layer`` (zeros when the tile has none: unknown)."""
        got = self.planes.get(layer)
        return got if got is not None else np.zeros((self.geometry.height,
                                                     self.geometry.width), np.int16)


@dataclass
class RefreshStats:
    """What the last :meth:`TileMirror.refresh` received: replies and their payload bytes."""

    replies: int = 0
    bytes: int = 0


class TileMirror:
    """The tiles of one region, held locally (module docstring)."""

    def __init__(self, session: zenoh.Session, keys: MapKeys, info: InfoReply, x: float,
                 y: float, width: float, height: float, timeout: float) -> None:
        if not (width > 0 and height > 0 and math.isfinite(width * height * x * y)):
            raise ValueError("a mirror's region needs a finite centre and a positive size")
        self.session = session
        self.keys = keys
        self.timeout = timeout
        self.resolution = info.resolution
        self.tile_size = info.tile_size
        self.expect = Expectation(info.map, info.resolution, info.tile_size, info.frame)
        span = info.resolution * info.tile_size
        self.bounds = (math.floor((x - width / 2) / span), math.floor((y - height / 2) / span),
                       max(math.floor((x - width / 2) / span),
                           math.ceil((x + width / 2) / span) - 1),
                       max(math.floor((y - height / 2) / span),
                           math.ceil((y + height / 2) / span) - 1))
        """Inclusive tile bounds ``(i0, j0, i1, j1)`` of the region."""
        self.tiles: dict[TileIndex, HeldTile] = {}
        self.last = RefreshStats()

    def versions(self) -> dict[TileIndex, int]:
        return {index: t.version for index, t in self.tiles.items()}

    def refresh(self, timeout: float | None = None) -> list[TileIndex]:
        """Pull the tiles of the region whose version differs from the one held (all of them
        the first time); returns the indices that changed, in reply order."""
        i0, j0, i1, j1 = self.bounds
        req = TilesChangedRequest(i0=i0, j0=j0, i1=i1, j1=j1,
                                  held=[(i, j, v) for (i, j), v in self.versions().items()])
        budget = timeout or self.timeout
        stats, changed, got = RefreshStats(), [], {}
        for reply in self.session.get(self.keys.tiles_changed, payload=codec.encode(req),
                                      accept_replies=zenoh.ReplyKeyExpr.ANY, timeout=budget):
            if reply.err is not None:
                payload = reply.err.payload.to_bytes()
                if payload == b"Timeout":
                    raise QueryTimeoutError(f"tiles/changed: no answer within {budget:g} s")
                raise service_error(payload)
            if reply.ok is None:
                continue
            blob = reply.ok.payload.to_bytes()
            stats.replies += 1
            stats.bytes += len(blob)
            index = tile_of_key(str(reply.ok.key_expr))
            got[index] = self._decode(index, blob)
        for index, tile in got.items():  # applied only once every reply decoded
            self.tiles[index] = tile
            changed.append(index)
        self.last = stats
        return changed

    def _decode(self, index: TileIndex, blob: bytes) -> HeldTile:
        tile = tile_from_bytes(blob, self.expect)
        h = tile.header
        if h.index != index:
            raise ValueError(f"a reply keyed tile {index} holds tile {h.index}")
        t = self.tile_size
        geometry = GridGeometry(self.resolution, t, t, Pose2D(*h.origin, 0.0))
        planes = {name: tile.data[k] for k, name in enumerate(h.layers)}
        return HeldTile(index, h.tile_version, planes, h.stamp, geometry, dict(h.decay))

    def layer(self, name: str, now: float | None = None,
              half_life: float | None = None) -> tuple[Fixed, GridGeometry]:
        """``(rows, cols)`` log-odds of ``name`` over the region's tiles (0: unknown or not
        held) and the geometry that places them.  For a decaying layer, with ``half_life``
        (s) and ``now`` (the map's clock, e.g. the newest stamp held), the cells as the server
        would read them then (:mod:`sogm_service.core.map.forget`)."""
        i0, j0, i1, j1 = self.bounds
        t = self.tile_size
        out = np.zeros(((j1 - j0 + 1) * t, (i1 - i0 + 1) * t), np.int16)
        for (i, j), tile in self.tiles.items():
            plane = tile.planes.get(name)
            if plane is None or not (i0 <= i <= i1 and j0 <= j <= j1):
                continue
            if half_life is not None and now is not None:
                since = tile.decay.get(name, tile.stamp)
                plane = forget.decayed(plane, forget.decay_factor(now - since, half_life))
            out[(j - j0) * t:(j - j0 + 1) * t, (i - i0) * t:(i - i0 + 1) * t] = plane
        span = self.resolution * t
        return out, GridGeometry(self.resolution, out.shape[1], out.shape[0],
                                 Pose2D(i0 * span, j0 * span, 0.0))
