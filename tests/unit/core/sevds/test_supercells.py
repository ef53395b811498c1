"""Supercell graph (paper Fig. 6, Eq. 11): centroids in map coordinates, adjacency, features."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.sevds.segment import SevdsParams
from sogm_service.core.sevds.supercells import adjacency, extract_supercells, supercell_graph

LABELS = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, 2]])


def stack_for_labels() -> np.ndarray:
    """Layer 0: label 0 cells 0.5, label 1 cells 0.8, label 2 cells 0.2; layer 1: all 0.5."""
    p = np.choose(LABELS, [0.5, 0.8, 0.2])
    return np.stack([p, np.full_like(p, 0.5)])


def test_adjacency_pairs() -> None:
    np.testing.assert_array_equal(adjacency(LABELS), [[0, 1], [0, 2], [1, 2]])
    assert adjacency(np.zeros((3, 3), int)).shape == (0, 2)


def test_centroids_areas_neighbours_in_map_frame() -> None:
    geo = GridGeometry(0.5, 4, 3, Pose2D(10.0, 20.0, 0.0))
    g = supercell_graph(LABELS, stack_for_labels(), geo)
    np.testing.assert_array_equal(g.areas, [4, 4, 4])
    # Label 0: mean (u, v) = (0.5, 0.5) -> corner + (u + 0.5) * res = (10.5, 20.5).
    # Label 2: mean (u, v) = (1.5, 2.0) -> (10 + 2 * 0.5, 20 + 2.5 * 0.5) = (11.0, 21.25).
    np.testing.assert_allclose(g.centroids[0], [10.5, 20.5])
    np.testing.assert_allclose(g.centroids[2], [11.0, 21.25])
    np.testing.assert_allclose(g.areas_m2, [1.0, 1.0, 1.0])
    assert g.neighbors() == [(1, 2), (0, 2), (0, 1)]


def test_centroids_follow_a_rotated_origin() -> None:
    geo = GridGeometry(0.5, 4, 3, Pose2D(10.0, 20.0, math.pi / 2))
    g = supercell_graph(LABELS, stack_for_labels(), geo)
    # Grid x axis points along world +y: (u, v) = (0.5, 0.5) -> (10 - 0.5, 20 + 0.5).
    np.testing.assert_allclose(g.centroids[0], [9.5, 20.5], atol=1e-12)


def test_eq11_feature_is_the_sum_of_log_odds() -> None:
    g = supercell_graph(LABELS, stack_for_labels())
    # Odd(0.8) = 4 per cell, four cells: product 4^4, i.e. 4 ln 4 nats; 0.5 cells add nothing.
    np.testing.assert_allclose(g.logodds_sum[:, 0], [0.0, 4 * math.log(4), 4 * math.log(0.25)])
    np.testing.assert_allclose(g.logodds_sum[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(g.mean_probability[:, 0], [0.5, 0.8, 0.2])


def test_certain_cells_are_clamped_like_the_map() -> None:
    p = np.ones((1, 1, 2))
    g = supercell_graph(np.zeros((1, 2), int), p, eps0=0.001)
    assert g.logodds_sum[0, 0] == pytest.approx(2 * math.log(0.999 / 0.001))


def test_fixed_point_stack_gives_exact_sums() -> None:
    fixed = np.full((1, 3, 4), 1000, np.int16)  # 1 nat per cell
    fixed[0, 2, :] = -500
    g = supercell_graph(LABELS, fixed)
    np.testing.assert_allclose(g.logodds_sum[:, 0], [4.0, 4.0, -2.0])
    np.testing.assert_allclose(g.mean_probability[:, 0],
                               [logodds.sigmoid(1.0)] * 2 + [logodds.sigmoid(-0.5)])


def test_nodes_match_the_arrays() -> None:
    geo = GridGeometry(0.1, 4, 3)
    g = supercell_graph(LABELS, stack_for_labels(), geo)
    nodes = g.nodes()
    assert [n.id for n in nodes] == [0, 1, 2]
    assert nodes[1].neighbors == (0, 2)
    assert nodes[1].area_m2 == pytest.approx(0.04)
    assert nodes[1].mean_probability == pytest.approx((0.8, 0.5))


def test_extract_supercells_end_to_end() -> None:
    rng = np.random.default_rng(4)
    stack = rng.random((3, 24, 32)).astype(np.float32)
    geo = GridGeometry(0.05, 32, 24, Pose2D(1.0, 2.0, 0.3))
    g, res = extract_supercells(stack, geo, SevdsParams(block_size=8))
    np.testing.assert_array_equal(g.labels, res.labels)
    assert g.count == 12 and g.areas.sum() == 24 * 32
    # Adjacency is symmetric and matches a brute-force scan of the label image.
    brute = {tuple(sorted((int(a), int(b)))) for a, b in zip(
        np.r_[res.labels[:, :-1].ravel(), res.labels[:-1].ravel()],
        np.r_[res.labels[:, 1:].ravel(), res.labels[1:].ravel()], strict=True) if a != b}
    assert {tuple(e) for e in g.edges.tolist()} == brute
    # Every centroid lies inside the window's footprint in the map frame.
    local = Pose2D(1.0, 2.0, 0.3).inverse().transform_points(g.centroids)
    assert np.all((local >= 0) & (local <= [32 * 0.05, 24 * 0.05]))


def test_bad_inputs() -> None:
    with pytest.raises(ValueError):
        supercell_graph(LABELS, np.full((1, 3, 4), 1.5))
    with pytest.raises(ValueError):
        supercell_graph(LABELS, np.zeros((1, 2, 4)))
    with pytest.raises(ValueError):
        supercell_graph(LABELS * 2, stack_for_labels())  # label 1 and 3 unused
