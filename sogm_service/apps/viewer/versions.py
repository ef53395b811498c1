"""Which display tiles changed: the map-tile versions under them, one check per round.

Every map tile carries a version that moves exactly when its content does (docs/tiles.md).
Once a round, the hub asks ``sogm/<map>/tiles/changed`` for the lattice tiles under the visible
display tiles with the versions it already holds
(:class:`~sogm_service.client.mirror.TileMirror`, built afresh per check over the hub's held
versions); the server answers only the tiles whose version moved.  A display tile is then asked
again (one sub-map query) only when the versions of the lattice tiles it covers differ from
those it was drawn from; an unchanged map costs one empty check per round and no sub-map.

The mirror's replies are whole tiles (zlib-compressed tile files): only their versions are
kept here (the planes are dropped at once), the pictures still come from sub-map queries at
the display tile's own resolution, so a zoomed-out view never downloads full-resolution cells
for its pixels.

A check is shared by every page for ``max_age`` seconds per region.  A region beyond
:data:`MAX_CHECK_TILES` lattice tiles (the server's default ``max_region_tiles``), or a check
the server refuses, gives ``None``: the caller then falls back to asking every visible display
tile once per round.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from sogm_service.apps.viewer.tiles import TileSpec
from sogm_service.client.mapclient import MapClient
from sogm_service.client.mirror import HeldTile, TileMirror
from sogm_service.wire.keys import MapKeys
from sogm_service.wire.queries import InfoReply

log = logging.getLogger("sogm_service.apps.viewer")

MAX_CHECK_TILES = 1024
"""Lattice tiles one check may cover (a larger region: every visible tile is asked instead)."""
MAX_HELD = 100_000
"""Tile versions remembered (the least recently changed are forgotten beyond this)."""

Bounds = tuple[int, int, int, int]
Source = tuple[tuple[int, int, int], ...]
"""What a display tile was drawn from: ``(i, j, version)`` of each known lattice tile under it."""


def lattice_bounds(specs: list[TileSpec]) -> Bounds | None:
    """Inclusive lattice tile bounds ``(i0, j0, i1, j1)`` under ``specs`` (None if empty)."""
    if not specs:
        return None
    i0 = min(s.a << s.level for s in specs)
    j0 = min(s.b << s.level for s in specs)
    i1 = max(((s.a + 1) << s.level) - 1 for s in specs)
    j1 = max(((s.b + 1) << s.level) - 1 for s in specs)
    return i0, j0, i1, j1


def region_size(bounds: Bounds) -> int:
    i0, j0, i1, j1 = bounds
    return (i1 - i0 + 1) * (j1 - j0 + 1)


def source_of(spec: TileSpec, versions: dict[tuple[int, int], int]) -> Source:
    """The versions of the known lattice tiles under one display tile."""
    n = 1 << spec.level
    i0, j0 = spec.a << spec.level, spec.b << spec.level
    if n * n <= len(versions):
        got = [(i, j, versions[(i, j)]) for j in range(j0, j0 + n) for i in range(i0, i0 + n)
               if (i, j) in versions]
    else:
        got = [(i, j, v) for (i, j), v in versions.items()
               if i0 <= i < i0 + n and j0 <= j < j0 + n]
    return tuple(sorted(got))


@dataclass
class CheckStats:
    """Every check so far: how many, and the replies and payload bytes they received."""

    checks: int = 0
    replies: int = 0
    bytes: int = 0
    failures: int = 0
    fallbacks: int = 0


class VersionBook:
    """The map-tile versions the viewer holds, refreshed by ``tiles/changed`` checks."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: OrderedDict[tuple[int, int], HeldTile] = OrderedDict()
        self._checked: OrderedDict[Bounds, float] = OrderedDict()
        self.stats = CheckStats()

    def clear(self) -> None:
        """Forget everything (another server process answers now)."""
        with self._lock:
            self._held.clear()
            self._checked.clear()

    def versions(self, client: MapClient, info: InfoReply, bounds: Bounds,
                 max_age: float, timeout: float) -> dict[tuple[int, int], int] | None:
        """The current version of every known tile within ``bounds``, or None when this
        region cannot be checked (too large, or refused: the caller asks every tile)."""
        if region_size(bounds) > MAX_CHECK_TILES:
            self.stats.fallbacks += 1
            return None
        with self._lock:
            fresh = time.monotonic() - self._checked.get(bounds, -1e18) < max_age
            if not fresh:
                self._check(client, info, bounds, timeout)
            i0, j0, i1, j1 = bounds
            return {idx: t.version for idx, t in self._held.items()
                    if i0 <= idx[0] <= i1 and j0 <= idx[1] <= j1}

    def _check(self, client: MapClient, info: InfoReply, bounds: Bounds,
               timeout: float) -> None:
        i0, j0, i1, j1 = bounds
        span = info.resolution * info.tile_size
        eps = span * 1e-6  # the box strictly inside the tiles' edges: exactly these bounds
        mirror = TileMirror(client.session, MapKeys(client.prefix, client.map_name), info,
                            (i0 + i1 + 1) * span / 2, (j0 + j1 + 1) * span / 2,
                            (i1 - i0 + 1) * span - eps, (j1 - j0 + 1) * span - eps, timeout)
        mirror.tiles = {idx: t for idx, t in self._held.items()
                        if i0 <= idx[0] <= i1 and j0 <= idx[1] <= j1}
        try:
            changed = mirror.refresh()
        except Exception:
            self.stats.failures += 1
            raise
        self.stats.checks += 1
        self.stats.replies += mirror.last.replies
        self.stats.bytes += mirror.last.bytes
        for idx in changed:
            tile = mirror.tiles[idx]
            tile.planes = {}  # only the version is needed: the pictures come from sub-maps
            self._held[idx] = tile
            self._held.move_to_end(idx)
        while len(self._held) > MAX_HELD:
            self._held.popitem(last=False)
        self._checked[bounds] = time.monotonic()
        self._checked.move_to_end(bounds)
        while len(self._checked) > 64:
            self._checked.popitem(last=False)
