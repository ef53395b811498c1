"""Segmentation metrics on small cases computed by hand (see the comments for the arithmetic)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sogm_service.eval import metrics

# A 2x4 grid split into two 2x2 superpixels; the ground truth splits it 3 columns | 1 column.
SP = np.array([[0, 0, 1, 1], [0, 0, 1, 1]])
GT = np.array([[0, 0, 0, 1], [0, 0, 0, 1]])
ROW = np.array([0.1, 0.3, 0.5, 0.9])
IMG = np.stack([ROW, ROW])


def test_pureness_eq12() -> None:
    # S0 is all class 0 -> 1; S1 holds classes 0,1,0,1 -> majority share 2/4; mean 0.75.
    assert metrics.pureness(SP, GT) == pytest.approx(0.75)
    # Uneven superpixels count equally (Eq. 12 averages over superpixels, not cells).
    sp = np.array([[0, 1, 1, 1]])
    gt = np.array([[5, 5, 7, 7]])
    assert metrics.pureness(sp, gt) == pytest.approx((1.0 + 2 / 3) / 2)


def test_pureness_perfect_and_sparse_labels() -> None:
    assert metrics.pureness(GT * 17 - 3, GT) == 1.0


def test_undersegmentation_error_neubert_protzel() -> None:
    # S0 inside G0 -> leak 0; S1 meets G0 (2 cells) and G1 (2 cells): min(2, 2) + min(2, 2) = 4.
    assert metrics.undersegmentation_error(SP, GT) == pytest.approx(4 / 8)
    assert metrics.undersegmentation_error(GT, GT) == 0.0
    # One superpixel over everything: G0 min(6, 2) + G1 min(2, 6) = 4 of 8 cells.
    assert metrics.undersegmentation_error(np.zeros_like(GT), GT) == pytest.approx(0.5)


def test_boundary_map_is_one_sided() -> None:
    b = metrics.boundary_map(np.array([[0, 0, 1], [2, 2, 1]]))
    expected = np.array([[True, True, False], [False, True, False]])
    np.testing.assert_array_equal(b, expected)


def test_boundary_recall_tolerance() -> None:
    # GT boundary cells: column 2 (its right neighbour differs); SP boundary: column 1.
    assert metrics.boundary_recall(SP, GT, r=0) == 0.0
    assert metrics.boundary_recall(SP, GT, r=1) == 1.0
    assert metrics.boundary_recall(GT, GT, r=0) == 1.0
    # No ground-truth boundary: nothing to recall.
    assert metrics.boundary_recall(SP, np.zeros_like(GT)) == 1.0


def test_boundary_recall_counts_partial_hits() -> None:
    gt = np.zeros((4, 4), int)
    gt[:, 2:] = 1  # boundary cells (v, 1) for v = 0..3
    sp = np.zeros((4, 4), int)
    sp[:2, 2:] = 1  # SP boundary at (0, 1), (1, 1) and the row below: (1, 2), (1, 3)
    assert metrics.boundary_recall(sp, gt, r=0) == pytest.approx(2 / 4)


def test_boundary_tolerance_rule() -> None:
    assert metrics.boundary_tolerance((256, 256)) == 1  # 0.0025 * 362 = 0.9
    assert metrics.boundary_tolerance((1000, 1000)) == 4  # 3.54


def test_intra_cluster_variation_by_hand() -> None:
    # S0 = {0.1, 0.3, 0.1, 0.3}: mu 0.2, sum sq 0.04, sqrt 0.2, /4 = 0.05.
    # S1 = {0.5, 0.9, 0.5, 0.9}: mu 0.7, sum sq 0.16, sqrt 0.4, /4 = 0.1.  Mean 0.075.
    assert metrics.intra_cluster_variation(SP, IMG) == pytest.approx(0.075)
    # A second layer 1 - p doubles every squared deviation: ICV grows by sqrt(2).
    two = np.stack([IMG, 1.0 - IMG])
    assert metrics.intra_cluster_variation(SP, two) == pytest.approx(0.075 * math.sqrt(2))
    assert metrics.intra_cluster_variation(SP, np.full((3, 2, 4), 0.4)) == pytest.approx(0.0)


def test_explained_variation_by_hand() -> None:
    # mu = 0.45; total = 2 * (0.35^2 + 0.15^2 + 0.05^2 + 0.45^2) = 0.7;
    # explained = 4 * (0.2 - 0.45)^2 + 4 * (0.7 - 0.45)^2 = 0.5.
    assert metrics.explained_variation(SP, IMG) == pytest.approx(0.5 / 0.7)
    two = np.stack([IMG, 1.0 - IMG, np.zeros_like(IMG)])
    assert metrics.explained_variation(SP, two) == pytest.approx(0.5 / 0.7)
    # One superpixel per cell explains everything, one for all explains nothing.
    assert metrics.explained_variation(np.arange(8).reshape(2, 4), IMG) == pytest.approx(1.0)
    assert metrics.explained_variation(np.zeros((2, 4), int), IMG) == pytest.approx(0.0)


def test_all_metrics_keys_and_segments() -> None:
    out = metrics.all_metrics(SP, IMG, GT)
    assert set(out) == {"pureness", "icv", "ev", "ue", "br"}
    assert out["ue"] == pytest.approx(0.5)
    # UE/BR use the segment image when given: one segment -> no boundary to miss, no leak.
    seg_out = metrics.all_metrics(SP, IMG, GT, segments=np.zeros_like(GT))
    assert seg_out["ue"] == 0.0 and seg_out["br"] == 1.0


def test_shape_mismatch_is_rejected() -> None:
    with pytest.raises(ValueError):
        metrics.undersegmentation_error(SP, GT[:, :3])
    with pytest.raises(ValueError):
        metrics.intra_cluster_variation(SP, IMG[:, :3])
