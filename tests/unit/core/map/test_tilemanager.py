"""Tile manager (hysteresis, ROI, late joiners) and the geodetic datum of tile origins."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sogm_service.core.geodesy import GeoPoint, LocalTangentPlane, radii_of_curvature
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tilemanager import (
    TileManager,
    TileSwitchEvent,
    hysteresis_from_fraction,
)
from sogm_service.core.map.tiletypes import tile_name, tile_token
from sogm_service.wire.messages import GeodeticFix

LATTICE = TileLattice(0.05, 256)  # span 12.8 m
SPAN = LATTICE.span


def drive(tm: TileManager, robot: str, xs: np.ndarray, ys: np.ndarray,
          t0: float = 0.0) -> list[tuple[TileSwitchEvent, float, float]]:
    """Feed a trajectory; return every event with the pose that caused it."""
    out = []
    for k, (x, y) in enumerate(zip(xs, ys, strict=True)):
        event = tm.update(robot, float(x), float(y), t0 + 0.1 * k)
        if event is not None:
            out.append((event, float(x), float(y)))
    return out


def test_first_pose_yields_event_then_quiet_inside_the_tile() -> None:
    tm = TileManager(LATTICE, 1.0, 1, map_name="lab")
    first = tm.update("r1", 3.0, 4.0, 10.0)
    assert first is not None
    assert (first.robot, first.index, first.stamp, first.previous) == ("r1", (0, 0), 10.0, None)
    assert first.name == "lab/tile_i+0000_j+0000"
    assert tm.update("r1", 12.0, 12.0, 11.0) is None
    assert tm.update("r1", 0.1, 0.1, 12.0) is None


def test_driving_east_across_three_edges_switches_exactly_there() -> None:
    h = 1.0
    tm = TileManager(LATTICE, h, 1)
    xs = np.arange(1.0, 45.0, 0.05)
    events = drive(tm, "r1", xs, np.full_like(xs, 5.0))
    assert [e.index for e, _, _ in events] == [(0, 0), (1, 0), (2, 0), (3, 0)]
    assert [e.previous for e, _, _ in events] == [None, (0, 0), (1, 0), (2, 0)]
    # Each switch happens at the first sample at least h past the edge, not at the edge.
    for (event, x, _), edge in zip(events[1:], (SPAN, 2 * SPAN, 3 * SPAN), strict=True):
        assert edge + h <= x < edge + h + 0.05 + 1e-9
        assert event.origin.x == pytest.approx(edge) and event.origin.y == 0.0


def test_zigzag_along_an_edge_within_the_hysteresis_does_not_flap() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    rng = np.random.default_rng(7)
    n = 2000
    # Along the x = 12.8 edge, crossing it every step by up to 0.9 m, drifting north.
    xs = SPAN + rng.uniform(-0.9, 0.9, n) * np.where(np.arange(n) % 2, 1, -1)
    ys = np.linspace(2.0, 10.0, n)
    events = drive(tm, "r1", xs, ys)
    assert [e.index for e, _, _ in events] == [(0, 0)]  # only the first pose


def test_without_hysteresis_the_same_zigzag_flaps() -> None:
    """Control for the test above: it would catch a manager that ignores the margin."""
    tm = TileManager(LATTICE, 0.0, 1)
    xs = SPAN + np.tile([-0.5, 0.5], 10)
    events = drive(tm, "r1", xs, np.full_like(xs, 5.0))
    assert len(events) == 20


def test_after_a_switch_the_old_edge_has_hysteresis_too() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    xs = np.array([5.0, SPAN + 1.01, SPAN - 0.5, SPAN - 0.99, SPAN + 0.2, SPAN - 1.01])
    events = drive(tm, "r1", xs, np.full_like(xs, 5.0))
    assert [(e.index, x) for e, x, _ in events] == [
        ((0, 0), 5.0), ((1, 0), SPAN + 1.01), ((0, 0), SPAN - 1.01)]


def test_corner_and_negative_tiles() -> None:
    tm = TileManager(LATTICE, 0.5, 0)
    assert tm.update("r", -0.1, -0.1, 0.0).index == (-1, -1)  # type: ignore[union-attr]
    assert tm.update("r", 0.4, 0.4, 1.0) is None  # within 0.5 m of the corner
    event = tm.update("r", 0.6, 0.4, 2.0)  # x passed, y did not: tile of the pose
    assert event is not None and event.index == (0, 0)
    assert event.origin.x == 0.0 and event.name.endswith(tile_token(0, 0))
    assert tile_token(-3, 12) == "i-0003_j+0012"


def test_pose_jump_switches_immediately() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    tm.update("r", 1.0, 1.0, 0.0)
    event = tm.update("r", 100.0, -50.0, 1.0)
    assert event is not None and event.index == LATTICE.tile_of(100.0, -50.0)


def test_non_finite_pose_is_rejected_and_changes_nothing() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    tm.update("r", 1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="not finite"):
        tm.update("r", math.nan, 1.0, 1.0)
    with pytest.raises(ValueError):
        tm.update("q", 1.0, math.inf, 1.0)
    assert set(tm.current_tiles()) == {"r"}
    assert tm.current_tile("r") == (0, 0)


def test_current_tiles_for_late_joiners_holds_each_robots_last_event() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    tm.update("a", 1.0, 1.0, 0.0)
    tm.update("b", -20.0, 30.0, 0.0)
    tm.update("a", SPAN + 2.0, 1.0, 5.0)
    current = tm.current_tiles()
    assert {r: e.index for r, e in current.items()} == {"a": (1, 0), "b": (-2, 2)}
    assert current["a"].stamp == 5.0
    current.clear()  # a copy: the manager is unaffected
    assert len(tm.current_tiles()) == 2


def test_regions_of_interest_and_their_changes() -> None:
    tm = TileManager(LATTICE, 1.0, 1)
    assert tm.roi_changes() == (set(), set())
    tm.update("a", 1.0, 1.0, 0.0)
    square = {(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)}
    assert tm.regions_of_interest() == square
    assert tm.roi_changes() == (square, set())
    assert tm.roi_changes() == (set(), set())
    tm.update("a", SPAN + 2.0, 1.0, 1.0)  # one tile east
    entered, left = tm.roi_changes()
    assert entered == {(2, -1), (2, 0), (2, 1)}
    assert left == {(-1, -1), (-1, 0), (-1, 1)}
    tm.update("b", 1.0, 1.0, 2.0)  # overlapping ROIs: union
    entered, left = tm.roi_changes()
    assert entered == {(-1, -1), (-1, 0), (-1, 1)} and left == set()
    assert tm.remove("a") and not tm.remove("a")
    entered, left = tm.roi_changes()
    assert entered == set() and left == {(2, -1), (2, 0), (2, 1)}
    assert tm.regions_of_interest() == square


def test_roi_radius_zero_and_two() -> None:
    assert len(TileManager(LATTICE, 1.0, 0).roi_of((3, 4))) == 1
    roi = TileManager(LATTICE, 1.0, 2).roi_of((3, 4))
    assert len(roi) == 25 and (1, 2) in roi and (5, 6) in roi and (6, 4) not in roi


def test_configuration_is_validated() -> None:
    with pytest.raises(ValueError):
        TileManager(LATTICE, -0.1, 1)
    with pytest.raises(ValueError):
        TileManager(LATTICE, SPAN, 1)
    with pytest.raises(ValueError):
        TileManager(LATTICE, 1.0, -1)
    assert hysteresis_from_fraction(LATTICE, 0.1) == pytest.approx(1.28)
    with pytest.raises(ValueError):
        hysteresis_from_fraction(LATTICE, 1.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)), min_size=1,
                max_size=80),
       st.floats(0.0, 3.0))
def test_switch_only_when_outside_the_band(steps: list[tuple[float, float]], h: float) -> None:
    """Invariant of any trajectory: a switch happens iff the pose left the current tile's
    band, and the new tile is the lattice tile of the pose."""
    lattice = TileLattice(0.05, 64)  # 3.2 m tiles so random walks cross many edges
    tm = TileManager(lattice, h, 1)
    x = y = 0.0
    tm.update("r", x, y, 0.0)
    for dx, dy in steps:
        before = tm.current_tile("r")
        assert before is not None
        x, y = x + dx, y + dy
        event = tm.update("r", x, y, 0.0)
        x0, y0 = before[0] * lattice.span, before[1] * lattice.span
        outside = not (x0 - h <= x < x0 + lattice.span + h
                       and y0 - h <= y < y0 + lattice.span + h)
        assert (event is not None) == outside
        if event is not None:
            assert event.index == lattice.tile_of(x, y) and event.previous == before


# -- geodetic datum -------------------------------------------------------------------------
def test_one_tile_east_and_north_move_the_datum_by_the_right_angle() -> None:
    # WGS-84 at 45 deg and 250 m above the ellipsoid: 12.8 m is 12.8 / ((N + h) cos lat) rad
    # of longitude and 12.8 / (M + h) rad of latitude (to ~1e-6 relative over 12.8 m).
    datum = GeodeticFix(latitude=45.0, longitude=7.0, altitude=250.0)
    tm = TileManager(LATTICE, 1.0, 1, datum=datum)
    origin = tm.tile_datum(0, 0)
    east = tm.tile_datum(1, 0)
    north = tm.tile_datum(0, 1)
    m, n = radii_of_curvature(45.0)
    deg_east = math.degrees(12.8 / ((n + 250.0) * math.cos(math.radians(45.0))))
    deg_north = math.degrees(12.8 / (m + 250.0))
    assert origin == GeoPoint(45.0, 7.0, 250.0)
    assert east is not None and north is not None
    assert east.longitude - 7.0 == pytest.approx(deg_east, rel=1e-6)
    # The tangent plane leaves the ellipsoid: 12.8^2 / 2R = 13 um up, a hair of latitude.
    assert east.latitude == pytest.approx(45.0, abs=1e-9)
    assert east.altitude == pytest.approx(250.0, abs=1e-4)
    assert north.latitude - 45.0 == pytest.approx(deg_north, rel=1e-6)
    assert north.longitude == pytest.approx(7.0, abs=1e-12)
    event = tm.update("r", SPAN * 3 + 1.0, -SPAN + 1.0, 0.0)
    assert event is not None and event.datum is not None
    assert event.datum == tm.tile_datum(3, -1)
    assert event.datum.longitude == pytest.approx(7.0 + 3 * deg_east, rel=1e-9)


def test_datum_at_the_equator_and_without_a_datum() -> None:
    tm = TileManager(LATTICE, 1.0, 1, datum=GeoPoint(0.0, 0.0))
    east = tm.tile_datum(1, 0)
    assert east is not None
    # At the equator the point 12.8 m east is (a, 12.8, 0) in ECEF: longitude atan2(12.8, a).
    assert east.longitude == pytest.approx(math.degrees(math.atan2(12.8, 6378137.0)), rel=1e-9)
    assert east.latitude == pytest.approx(0.0, abs=1e-12)
    plain = TileManager(LATTICE, 1.0, 1)
    assert plain.tile_datum(1, 0) is None
    event = plain.update("r", 1.0, 1.0, 0.0)
    assert event is not None and event.datum is None
    assert event.as_dict()["datum"] is None and event.as_dict()["i"] == 0


def test_tangent_plane_round_trip_and_radii() -> None:
    m, n = radii_of_curvature(0.0)
    assert n == pytest.approx(6378137.0) and m == pytest.approx(6335439.327, rel=1e-9)
    plane = LocalTangentPlane(GeoPoint(52.5, 13.4, 34.0))
    rng = np.random.default_rng(3)
    for x, y, z in rng.uniform(-2000, 2000, (20, 3)):
        back = plane.to_map(plane.to_geodetic(x, y, z))
        assert back == pytest.approx((x, y, z), abs=1e-6)
    with pytest.raises(ValueError):
        LocalTangentPlane(GeoPoint(90.0, 0.0))


def test_longitude_wraps_at_the_antimeridian() -> None:
    plane = LocalTangentPlane(GeoPoint(0.0, 179.9999))
    p = plane.to_geodetic(100.0, 0.0)
    assert -180.0 <= p.longitude < -179.99
    assert plane.to_map(p)[0] == pytest.approx(100.0, abs=1e-6)


def test_tile_names_are_unique_per_map() -> None:
    assert tile_name("a", 1, 2) != tile_name("b", 1, 2) != tile_name("a", 2, 1)
