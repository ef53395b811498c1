"""The viewer's display tiles (apps/viewer/tiles): the level for a view, the visible tiles,
views refused with a code.

Its map constants (``RES`` and two layer names) are the viewer integration tests' too."""

from __future__ import annotations

import pytest

from sogm_service.apps.viewer.tiles import (
    Lattice,
    View,
    ViewError,
    known_at_level,
    parse_view,
    visible_tiles,
)

RES = 0.05
OBSTACLE = "r1/laser/obstacle"
CHAIR = "r1/cam/chair"


def test_level_is_the_finest_whose_pixels_cover_a_screen_pixel() -> None:
    lat = Lattice(RES, 256)
    assert lat.span == pytest.approx(12.8)
    assert lat.level_for(20.0) == 0  # 1 cell = 1 screen px at 20 px/m
    assert lat.level_for(100.0) == 0
    assert lat.level_for(19.0) == 1  # a cell would be < 1 px: one level coarser
    assert lat.level_for(5.0) == 2
    assert lat.level_for(5.0 / 1024) == 12
    assert lat.level_for(0.0) == lat.level_for(float("nan")) == 16


def test_visible_tiles_are_the_known_ones_in_the_box_nearest_first_and_bounded() -> None:
    lat = Lattice(RES, 256)
    known = {(0, 0), (1, 0), (5, 5), (-1, -1), (40, 0)}
    view = View(-1.0, -1.0, 30.0, 10.0, 20.0)
    specs = visible_tiles(view, lat, known_at_level(known, 0), 0)
    assert [(s.a, s.b) for s in specs] == [(1, 0), (0, 0), (-1, -1)]  # (5, 5), (40, 0) outside
    assert specs[0].x0 == pytest.approx(12.8) and specs[0].resolution == pytest.approx(RES)
    assert specs[0].key == "class|0|1|0"
    # one level up, four lattice tiles per display tile; negatives floor
    assert known_at_level(known, 1) == {(0, 0), (2, 2), (-1, -1), (20, 0)}
    many = {(i, j) for i in range(30) for j in range(30)}
    big = View(0.0, 0.0, 30 * 12.8, 30 * 12.8, 20.0)
    assert len(visible_tiles(big, lat, many, 0, limit=10)) == 10
    # a huge box over a small map walks the map, not the box
    huge = View(-1e6, -1e6, 1e6, 1e6, 1e-3)
    assert {(s.a, s.b) for s in visible_tiles(huge, lat, known, 0)} == known


def test_parse_view_accepts_a_good_view_and_refuses_bad_ones_with_a_code() -> None:
    layers = [OBSTACLE, CHAIR]
    good = {"xmin": 0, "ymin": 0, "xmax": 10, "ymax": 5, "px_per_m": 30, "mode": "fused",
            "method": "max", "layers": [CHAIR, "nope", OBSTACLE]}
    view = parse_view(good, layers)
    assert view.layers == (OBSTACLE, CHAIR) and view.signature() == f"fused:max:{OBSTACLE},{CHAIR}"
    assert parse_view({**good, "mode": "layer", "layer": CHAIR}, layers).signature() \
        == f"layer:{CHAIR}"
    bad = [({**good, "xmin": float("nan")}, "bad_view"), ({**good, "xmax": -1}, "bad_view"),
           ({**good, "px_per_m": 0}, "bad_view"), ({**good, "xmax": 1e9}, "bad_view"),
           ({**good, "xmin": "a"}, "bad_view"), ({**good, "mode": "rm -rf"}, "bad_mode"),
           ({**good, "method": "sum"}, "bad_method"), ({**good, "layers": "x"}, "bad_layers"),
           ({**good, "mode": "layer", "layer": "nope"}, "unknown_layer")]
    for msg, code in bad:
        with pytest.raises(ViewError) as exc:
            parse_view(msg, layers)
        assert exc.value.code == code, msg
