"""A cluster member's gathered map (service/cluster/gathered): a window read through it equals
the whole map's, on the full path (a mosaic at map resolution) and on the coarse path (only the
cells the warp interpolates from), and a tile whose owner does not answer fails the read
instead of reading as unknown."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tile import Tile
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.cluster.gathered import GatheredMap
from sogm_service.wire.errors import QueryError

RES = 0.25
T = 16
LAYER = "r1/laser/obstacle"


def _whole_map() -> TiledMap:
    """A 4 x 4-tile map, every cell known (mild random increments)."""
    rng = np.random.default_rng(5)
    tiled = TiledMap("m", "map", TileLattice(RES, T))
    inc = rng.integers(20, 301, (4 * T, 4 * T)).astype(np.int16)
    inc[rng.random(inc.shape) < 0.5] *= -1
    tiled.fuse(LAYER, inc, GridGeometry(RES, 4 * T, 4 * T, Pose2D(0.0, 0.0, 0.0)), "nearest")
    return tiled


class _Owners:
    """The cluster as a gathered map asks it: this member serves the tiles of ``mine``; the
    others come from ``whole`` (their owners), or no owner answers for those in ``silent``."""

    def __init__(self, whole: TiledMap, mine: set[TileIndex],
                 silent: frozenset[TileIndex] = frozenset()) -> None:
        self.whole, self.mine, self.silent = whole, mine, silent
        self.fetched: list[TileIndex] = []

    def serves(self, index: TileIndex) -> bool:
        return index in self.mine

    def fetch(self, indices: list[TileIndex]) -> dict[TileIndex, Tile | None]:
        for index in indices:
            if index in self.silent:
                raise QueryError("no_owner", f"no owner of tile {index} answered", "x")
        self.fetched += indices
        return {index: self.whole.tiles.get(index) for index in indices}


def _member(whole: TiledMap, mine: set[TileIndex]) -> TiledMap:
    """A member's own map: the tiles of ``mine`` only."""
    local = TiledMap("m", "map", TileLattice(RES, T))
    for index in sorted(mine):
        snap = whole.snapshot(index)
        assert snap is not None
        local.insert_tile(index, snap.layers, snap.data, snap.stamp, saved=True)
    return local


MINE = {(i, j) for i in range(4) for j in range(4) if (i + 2 * j) % 3}  # 2/3 of the tiles


@pytest.mark.parametrize("resolution", [RES, 2 * RES, 4 * RES])
def test_a_window_through_a_member_equals_the_whole_map(resolution: float) -> None:
    """At map resolution (the mosaic path) and coarser (the gather path, which reads only the
    cells the warp interpolates from: those of tiles the member does not own come from their
    owners too, never as unknown)."""
    whole = _whole_map()
    owners = _Owners(whole, MINE)
    gathered = GatheredMap(_member(whole, MINE), owners)
    n = round(4 * T * RES / resolution)
    window = GridGeometry(resolution, n, n, Pose2D(0.0, 0.0, 0.0))
    want = whole.sample(window, [LAYER], "biodds")
    got = gathered.sample(window, [LAYER], "biodds")
    assert np.count_nonzero(want) >= 0.99 * want.size  # (almost) every cell known
    assert np.array_equal(got, want)
    inside = {(i, j) for i in range(4) for j in range(4)}
    assert set(owners.fetched) & inside == inside - MINE  # (and the margin's tiles around)


@pytest.mark.parametrize("resolution", [RES, 4 * RES])
def test_a_tile_nobody_answers_for_fails_the_read(resolution: float) -> None:
    whole = _whole_map()
    gathered = GatheredMap(_member(whole, MINE), _Owners(whole, MINE, frozenset({(0, 0)})))
    n = round(4 * T * RES / resolution)
    window = GridGeometry(resolution, n, n, Pose2D(0.0, 0.0, 0.0))
    with pytest.raises(QueryError) as caught:
        gathered.sample(window, [LAYER], "biodds")
    assert caught.value.code == "no_owner" and "(0, 0)" in str(caught.value)
