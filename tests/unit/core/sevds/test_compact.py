"""Supercells are compact and connected, nodes sit inside them and say what evidence they have."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sogm_service.core.sevds.segment import Criterion, SevdsParams, sevds
from sogm_service.core.sevds.supercells import (
    FREE,
    UNKNOWN,
    extract_supercells,
    nearest_cells,
    node_evidence,
    supercell_graph,
)
from sogm_service.eval.rooms import room_scene


def walled_room(size: int = 120, wall: int = 10) -> np.ndarray:
    """One occupancy layer: unknown outside, a one-cell wall ring, free floor inside."""
    p = np.full((size, size), 0.5, np.float32)
    p[wall:size - wall, wall:size - wall] = 0.95
    p[wall + 1:size - wall - 1, wall + 1:size - wall - 1] = 0.05
    return p[None]


def extents(labels: np.ndarray) -> np.ndarray:
    """``(S, 2)`` rows and columns each label spans."""
    out = []
    for k in range(int(labels.max()) + 1):
        v, u = np.nonzero(labels == k)
        out.append((v.max() - v.min() + 1, u.max() - u.min() + 1))
    return np.array(out)


def wall_pieces(labels: np.ndarray, wall: np.ndarray) -> int:
    return len(np.unique(labels[wall]))


@pytest.mark.parametrize("block", [8, 16])
def test_a_thin_wall_ring_is_cut_into_pieces_within_the_extent_bound(block: int) -> None:
    stack = walled_room()
    wall = stack[0] > 0.9
    p = SevdsParams(block_size=block)
    labels = sevds(stack, p).labels
    assert extents(labels).max() <= p.extent * block
    # The ring is 4 * 99 cells long: no piece holds more than its extent allows.
    assert wall_pieces(labels, wall) >= wall.sum() / (2 * p.extent * block)
    # The bound is what cuts it: without it (the widest extent) a supercell grows longer.
    loose = sevds(stack, SevdsParams(block_size=block, extent=64.0)).labels
    assert extents(loose).max() > p.extent * block


def test_the_extent_bound_holds_on_a_room_map_for_both_criteria() -> None:
    scene = room_scene(1)
    for criterion in ("energy", "distribution"):
        for extent in (1.5, 4.0):
            p = SevdsParams(block_size=8, criterion=criterion, extent=extent)
            labels = sevds(scene.stack, p).labels
            assert extents(labels).max() <= 8 + 2 * p.margin <= extent * 8


@pytest.mark.parametrize("criterion", ["energy", "distribution"])
def test_every_supercell_is_one_connected_region(criterion: Criterion) -> None:
    rng = np.random.default_rng(3)
    noisy = rng.random((2, 96, 80), dtype=np.float32)
    for stack in (room_scene(2).stack, noisy, walled_room()):
        labels = sevds(stack, SevdsParams(block_size=8, criterion=criterion)).labels
        for k in range(int(labels.max()) + 1):
            n, _ = cv2.connectedComponents((labels == k).astype(np.uint8), connectivity=4)
            assert n == 2, f"supercell {k} is in {n - 1} pieces"


def test_the_node_of_a_ring_sits_on_the_ring_not_in_its_hole() -> None:
    labels = np.zeros((9, 9), np.int32)
    labels[2:7, 2:7] = 1  # label 0 rings label 1: its centroid (4, 4) lies in label 1
    g = supercell_graph(labels, np.full((1, 9, 9), 0.5, np.float32))
    np.testing.assert_allclose(g.centroids_cell[0], [4.0, 4.0])
    u, v = g.nodes_cell[0]
    assert labels[v, u] == 0
    assert abs(u - 4) + abs(v - 4) == 3  # the ring's nearest cells to (4, 4)
    assert g.nodes_cell[1].tolist() == [4, 4]  # a convex supercell: its centroid's cell
    np.testing.assert_allclose(g.positions[1], g.centroids[1])
    assert g.nodes()[0].x == pytest.approx(g.positions[0, 0])


def test_nearest_cells_takes_the_first_cell_in_raster_order_on_ties() -> None:
    labels = np.array([[0, 1, 0]], np.int32)
    assert nearest_cells(labels, np.array([[1.0, 0.0], [1.0, 0.0]])).tolist() == [[0, 0], [1, 0]]


@pytest.mark.parametrize("block", [8, 16])
def test_every_node_of_a_room_map_lies_in_its_own_supercell(block: int) -> None:
    scene = room_scene(0)
    g, _ = extract_supercells(scene.stack, params=SevdsParams(block_size=block))
    u, v = g.nodes_cell.T
    assert (g.labels[v, u] == np.arange(g.count)).all()
    # The node is the supercell's cell nearest its centroid: no cell of it is nearer.
    d_node = np.hypot(*(g.nodes_cell - g.centroids_cell).T)
    vv, uu = np.indices(g.labels.shape)
    d_all = np.hypot(uu - g.centroids_cell[g.labels, 0], vv - g.centroids_cell[g.labels, 1])
    assert (d_all >= d_node[g.labels] - 1e-9).all()


def test_free_floor_is_evidence() -> None:
    stack = walled_room()
    g, _ = extract_supercells(stack, params=SevdsParams(block_size=8))
    ev = g.evidence()
    cells = np.bincount(g.labels.ravel(), minlength=g.count)

    def only(mask: np.ndarray) -> np.ndarray:  # supercells wholly of these cells
        return np.bincount(g.labels[mask], minlength=g.count) == cells

    floor, outside, wall = only(stack[0] < 0.1), only(stack[0] == 0.5), only(stack[0] > 0.9)
    assert floor.sum() > 20 and outside.sum() > 20 and wall.any()
    assert (ev[floor] == FREE).all()  # observed free floor: evidence, not "without evidence"
    assert (ev[outside] == UNKNOWN).all()
    assert (ev[wall] == 0).all()  # a wall piece: its layer, occupied


def test_node_evidence_rule() -> None:
    mp = np.array([[0.5, 0.5], [0.2, 0.5], [0.2, 0.8], [0.505, 0.495], [0.6, 0.9]])
    assert node_evidence(mp).tolist() == [UNKNOWN, FREE, 1, UNKNOWN, 1]
    assert node_evidence(np.zeros((0, 3))).size == 0
    with pytest.raises(ValueError):
        node_evidence(np.array([0.5, 0.2]))


def test_extent_is_validated() -> None:
    for bad in (0.5, 65.0, float("nan")):
        with pytest.raises(ValueError, match="extent"):
            SevdsParams(extent=bad)
    assert SevdsParams(block_size=8, extent=3.0).margin == 8
    assert SevdsParams(block_size=8, extent=1.0).margin == 0
    assert SevdsParams(block_size=8).margin == 12  # the default: 4 blocks across
