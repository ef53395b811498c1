"""The laser inverse sensor model: free along beams, occupied at hits, unknown beyond."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sogm_service.adapters.laser import (
    encode_occupancy_i8,
    encode_prob_u8,
    encode_prob_u8_v2,
    laser_ism,
    scan_endpoints_world,
)
from sogm_service.core.geometry import GridGeometry, Pose2D

RES = 0.1


def prob_at(geom: GridGeometry, p: np.ndarray, x: float, y: float) -> float:
    """ISM probability of the cell containing map-frame point (x, y)."""
    u, v = geom.world_to_index(np.array([x, y]))
    return float(p[v, u])


def test_single_beam_free_then_hit_then_unknown() -> None:
    geom, p = laser_ism([2.0], [0.0], Pose2D(), RES, max_range=5.0)
    assert geom.origin.yaw == 0.0
    for x in (0.05, 0.55, 1.05, 1.75):  # along the beam, short of the hit
        assert prob_at(geom, p, x, 0.01) == np.float32(0.3)
    assert prob_at(geom, p, 2.0 + 0.01, 0.01) == np.float32(0.8)
    assert (p == np.float32(0.8)).sum() == 1
    assert prob_at(geom, p, 2.15, 0.01) == 0.5  # beyond the hit
    assert prob_at(geom, p, 1.05, 0.15) == 0.5  # beside the beam


def test_unknown_is_exactly_half_and_beyond_hit_unknown() -> None:
    # A long beam and a short one at the same bearing region: behind the short hit nothing
    # is free from that beam, so with a fan of short beams the area behind is unknown.
    angles = np.linspace(-0.3, 0.3, 61)
    ranges = np.where(np.abs(angles) < 0.1, 1.0, 3.0)
    geom, p = laser_ism(ranges, angles, Pose2D(), RES, max_range=5.0)
    assert prob_at(geom, p, 2.0, 0.0) == 0.5  # behind the near obstacle
    assert prob_at(geom, p, 2.0, 0.5) == np.float32(0.3)  # free on a long beam
    assert set(np.unique(p)) <= {np.float32(0.3), np.float32(0.5), np.float32(0.8)}


def test_max_range_beam_is_free_without_hit() -> None:
    geom, p = laser_ism([10.0], [0.0], Pose2D(), RES, max_range=3.0)
    assert (p == np.float32(0.8)).sum() == 0
    assert prob_at(geom, p, 2.95, 0.01) == np.float32(0.3)
    assert geom.size_m[0] <= 3.0 + 3 * RES + 1e-9  # the box stops at max_range (+ padding)


def test_invalid_and_no_return_readings_are_dropped() -> None:
    geom, p = laser_ism([np.nan, 0.0, -1.0, np.inf, 81.83], [0, 0.1, 0.2, 0.3, 0.4], Pose2D(),
                        RES, max_range=20.0, device_max_range=80.0)
    assert (p == 0.5).all()
    assert geom.width * geom.height <= 9  # only the sensor's own cells and the padding


def test_rotated_sensor_grid_is_sensor_aligned_and_hits_land_on_endpoints() -> None:
    pose = Pose2D(3.0, -2.0, 2.2)
    angles = np.linspace(-1.0, 1.0, 41) + 0.0123  # keep ends off exact cell boundaries
    ranges = 1.5 + 0.5 * np.cos(3 * angles)
    geom, p = laser_ism(ranges, angles, pose, 0.05, max_range=10.0)
    assert math.isclose(geom.origin.yaw, 2.2)
    ends = scan_endpoints_world(ranges, angles, pose, 10.0)
    uv = geom.world_to_index(ends)
    assert (p[uv[:, 1], uv[:, 0]] == np.float32(0.8)).all()
    assert (p == np.float32(0.8)).sum() <= len(angles)


def test_hit_width_widens_hits() -> None:
    _, p1 = laser_ism([2.0], [0.0], Pose2D(), RES, 5.0)
    _, p3 = laser_ism([2.0], [0.0], Pose2D(), RES, 5.0, hit_width_cells=3)
    assert (p1 == np.float32(0.8)).sum() == 1
    assert (p3 == np.float32(0.8)).sum() == 9


@settings(max_examples=40, deadline=None)
@given(
    x=st.floats(-50, 50), y=st.floats(-50, 50), yaw=st.floats(-math.pi, math.pi),
    ranges=st.lists(st.floats(0.05, 6.0), min_size=1, max_size=60),
)
def test_every_hit_is_occupied_and_nothing_else_is(
        x: float, y: float, yaw: float, ranges: list[float]) -> None:
    angles = np.linspace(-2.0, 2.0, len(ranges)) + 0.0123  # off exact cell boundaries
    pose = Pose2D(x, y, yaw)
    geom, p = laser_ism(ranges, angles, pose, 0.05, max_range=4.0)
    ends = scan_endpoints_world(ranges, angles, pose, 4.0)
    if len(ends):
        uv = geom.world_to_index(ends)
        assert (p[uv[:, 1], uv[:, 0]] == np.float32(0.8)).all()
    assert (p == np.float32(0.8)).sum() <= len(ends)
    assert p.dtype == np.float32


def test_encoders() -> None:
    p = np.array([0.0, 0.3, 0.5, 0.8, 1.0], dtype=np.float32)
    assert encode_occupancy_i8(p).tolist() == [0, 30, -1, 80, 100]
    assert encode_prob_u8(p).tolist() == [0, 77, 128, 204, 255]


def test_laser_encoder_writes_unknown_as_255() -> None:
    assert encode_prob_u8_v2(np.array([0.0, 0.5, 1.0, np.nan, 0.25])).tolist() == \
        [0, 255, 254, 255, round(0.25 * 254)]
