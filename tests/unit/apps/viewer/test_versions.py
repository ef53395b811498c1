"""The viewer's version book helpers (apps/viewer/versions): which lattice tiles a round checks
and which versions a display tile is drawn from."""

from __future__ import annotations

from sogm_service.apps.viewer.tiles import TileSpec
from sogm_service.apps.viewer.versions import lattice_bounds, region_size, source_of


def spec(level: int, a: int, b: int) -> TileSpec:
    span = 12.8 * (1 << level)
    return TileSpec("class", level, a, b, a * span, b * span, span, 256)


def test_a_round_checks_exactly_the_lattice_tiles_under_its_display_tiles() -> None:
    assert lattice_bounds([]) is None
    assert lattice_bounds([spec(0, 2, -1)]) == (2, -1, 2, -1)
    # level 1: (a, b) = (-1, 0) covers lattice i -2..-1, j 0..1; (1, 1) covers i 2..3, j 2..3
    bounds = lattice_bounds([spec(1, -1, 0), spec(1, 1, 1)])
    assert bounds == (-2, 0, 3, 3)
    assert region_size(bounds) == 6 * 4


def test_a_display_tile_is_drawn_from_the_versions_of_its_own_lattice_tiles() -> None:
    versions = {(0, 0): 5, (1, 1): 7, (2, 0): 9, (-1, 0): 3}
    assert source_of(spec(1, 0, 0), versions) == ((0, 0, 5), (1, 1, 7))
    assert source_of(spec(0, 2, 0), versions) == ((2, 0, 9),)
    assert source_of(spec(0, 5, 5), versions) == ()
    # a version that moves changes the source of the tiles over it and of no other
    moved = {**versions, (1, 1): 8}
    assert source_of(spec(1, 0, 0), moved) != source_of(spec(1, 0, 0), versions)
    assert source_of(spec(0, 2, 0), moved) == source_of(spec(0, 2, 0), versions)
    # a coarse tile over few known tiles walks the versions, with the same answer
    assert source_of(spec(4, -1, 0), versions) == ((-1, 0, 3),)
    assert source_of(spec(4, -1, -1), versions) == ()
    assert source_of(spec(4, 0, 0), versions) == ((0, 0, 5), (1, 1, 7), (2, 0, 9))
