"""SEVDS (paper Eq. 7-10): invariants, the paper's corner-case rule, the criteria, speed hooks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sogm_service.bench.sevds import benchmark_sevds_vs_seeds
from sogm_service.core.sevds.segment import (
    SevdsParams,
    bin_centres,
    histogram_variance,
    quantize,
    sevds,
)


def two_regions(h: int = 32, w: int = 32, cut: int = 13, noise: float = 0.0,
                seed: int = 0) -> np.ndarray:
    """Two layers: region left of ``cut`` is (0.9, 0.1), right of it (0.1, 0.9)."""
    rng = np.random.default_rng(seed)
    left = np.zeros((h, w), bool)
    left[:, :cut] = True
    stack = np.stack([np.where(left, 0.9, 0.1), np.where(left, 0.1, 0.9)])
    stack = stack + rng.normal(0.0, noise, stack.shape)
    return np.clip(stack, 0.0, 1.0).astype(np.float32)


def independent_hist(stack: np.ndarray, labels: np.ndarray, bins: int) -> np.ndarray:
    """Per-layer histograms recomputed from scratch with np.histogram-like binning."""
    q = np.minimum((stack * bins).astype(int), bins - 1)
    count = labels.max() + 1
    out = np.zeros((count, stack.shape[0], bins), int)
    for c in range(count):
        for n in range(stack.shape[0]):
            out[c, n] = np.bincount(q[n][labels == c], minlength=bins)
    return out


def energy(stack: np.ndarray, labels: np.ndarray, bins: int, gamma: float) -> float:
    """E = sum_c |c| D'(c) + gamma * sum_c perimeter(c), from scratch."""
    hist = independent_hist(stack, labels, bins)
    sizes = hist[:, 0].sum(axis=1)
    sse = float(np.sum(sizes * histogram_variance(hist).sum(axis=1)))
    edges = np.count_nonzero(labels[:, 1:] != labels[:, :-1]) + np.count_nonzero(
        labels[1:] != labels[:-1])
    return sse + gamma * 2.0 * edges


def test_histogram_variance_is_the_variance_of_the_binned_values() -> None:
    # K = 4, centres 1/8, 3/8, 5/8, 7/8; two cells at 1/8 and two at 5/8: mean 3/8, var (1/4)^2.
    assert histogram_variance([2, 0, 2, 0]) == pytest.approx(1 / 16)
    assert histogram_variance([0, 5, 0, 0]) == 0.0
    np.testing.assert_allclose(bin_centres(4), [0.125, 0.375, 0.625, 0.875])


def test_block_levels_halve_while_divisible() -> None:
    assert SevdsParams(block_size=8, levels=3).block_sizes() == [4, 2]
    assert SevdsParams(block_size=12, levels=3).block_sizes() == [6, 3]
    assert SevdsParams(block_size=10, levels=4).block_sizes() == [5]
    assert SevdsParams(block_size=8, levels=1).block_sizes() == []


def test_energy_criterion_snaps_to_a_boundary_off_the_grid() -> None:
    stack = two_regions(noise=0.03)
    gt = np.zeros((32, 32), int)
    gt[:, 13:] = 1
    res = sevds(stack, SevdsParams(block_size=8, levels=3, gamma=0.05, criterion="energy"))
    # The initial 8x8 grid cuts the column-13 boundary inside a block column; after SEVDS no
    # supercell mixes the two regions.
    for c in range(res.count):
        assert len(np.unique(gt[res.labels == c])) == 1, f"supercell {c} straddles"
    assert res.moves > 0


@pytest.mark.parametrize("criterion", ["distribution", "energy"])
def test_cells_join_the_supercell_whose_variance_they_lower(criterion: str) -> None:
    # A = columns 0-7: 0.1 except column 7 at 0.9; B = columns 8-15: 0.9 except column 15 at
    # 0.1.  A 0.9 cell of column 7 lowers B's variance when it joins B (the paper's receiver
    # test D(c_hat) < D(c)) and lowers both SSEs (energy); a 0.1 cell of A would raise B's.
    one = np.full((1, 8, 16), 0.1, np.float32)
    one[0, :, 7:15] = 0.9
    res = sevds(one, SevdsParams(block_size=8, levels=1, iterations=3, gamma=0.0,
                                 criterion=criterion))  # type: ignore[arg-type]
    np.testing.assert_array_equal(res.labels[:, 7], 1)
    np.testing.assert_array_equal(res.labels[:, :7], 0)
    np.testing.assert_array_equal(res.labels[:, 8:], 1)


@pytest.mark.parametrize("criterion", ["distribution", "energy"])
def test_state_stays_consistent(criterion: str) -> None:
    rng = np.random.default_rng(3)
    stack = rng.random((3, 27, 20)).astype(np.float32)  # sizes not divisible by the block
    res = sevds(stack, SevdsParams(block_size=8, criterion=criterion))  # type: ignore[arg-type]
    assert res.labels.shape == (27, 20)
    assert res.count == 4 * 3  # ceil(27/8) * ceil(20/8), none emptied
    np.testing.assert_array_equal(res.histograms, independent_hist(stack, res.labels,
                                                                   SevdsParams().bins))
    for c in range(res.count):
        n, _ = cv2.connectedComponents((res.labels == c).astype(np.uint8), connectivity=4)
        assert n - 1 == 1, f"supercell {c} is not one 4-connected piece"


def test_energy_criterion_lowers_the_total_energy() -> None:
    rng = np.random.default_rng(5)
    stack = two_regions(noise=0.15, seed=2)
    stack = np.concatenate([stack, rng.random((1, 32, 32)).astype(np.float32)])
    p = SevdsParams(block_size=8, gamma=0.05, criterion="energy")
    res = sevds(stack, p)
    initial = (np.arange(32)[:, None] // 8) * 4 + np.arange(32)[None, :] // 8
    assert energy(stack, res.labels, p.bins, p.gamma) < energy(stack, initial, p.bins, p.gamma)


def test_zero_variance_supercells_do_not_shrink() -> None:
    # Supercell A (left 8x8) is homogeneous; B (right 8x8) is mostly the same value with four
    # contradicting cells at its far right.  Adding one of A's cells would lower B's variance,
    # so the receiver-only criterion alone would take cells from A; the paper's rule forbids it.
    one = np.full((1, 8, 16), 0.1, np.float32)
    one[0, 2:6, 15] = 0.9
    hist_b = np.array([60, 0, 0, 0, 4])
    assert histogram_variance(hist_b + np.array([1, 0, 0, 0, 0])) < histogram_variance(hist_b)
    res = sevds(one, SevdsParams(block_size=8, levels=1, iterations=4, gamma=0.0))
    assert np.count_nonzero(res.labels == 0) >= 64
    assert np.all(res.labels[:, :8] == 0)


def test_linear_in_layers_and_no_joint_histogram() -> None:
    rng = np.random.default_rng(1)
    stack = rng.random((16, 24, 24)).astype(np.float32)
    res = sevds(stack, SevdsParams(block_size=8, bins=8))
    assert res.histograms.shape == (9, 16, 8)  # marginals only: S x N x K, not K**N
    assert res.distribution().shape == (9,)


def test_constant_input_does_not_move() -> None:
    res = sevds(np.full((2, 16, 16), 0.5, np.float32), SevdsParams(block_size=8, gamma=0.3))
    assert res.moves == 0
    np.testing.assert_array_equal(res.distribution(), 0.0)


def test_quantize_edges() -> None:
    q = quantize(np.array([[[0.0, 0.19, 0.2, 0.999, 1.0]]]), 5)
    np.testing.assert_array_equal(q[0, 0], [0, 0, 1, 4, 4])


def test_bad_input_is_rejected() -> None:
    with pytest.raises(ValueError):
        sevds(np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError):
        sevds(np.full((1, 8, 8), np.nan, np.float32))
    for bad in ({"block_size": 0}, {"bins": 1}, {"gamma": -1.0}, {"criterion": "x"},
                {"levels": 0}, {"iterations": -1}):
        with pytest.raises(ValueError):
            SevdsParams(**bad)


def test_benchmark_reports_timings_and_skips_seeds_when_too_big() -> None:
    rows = benchmark_sevds_vs_seeds((2, 8), height=32, width=32, repeats=1,
                                    seeds_memory_limit=10 << 20)
    assert [r["layers"] for r in rows] == [2, 8]
    small, big = rows
    assert isinstance(small["sevds_s"], float) and small["sevds_s"] > 0
    assert isinstance(small["seeds_s"], float) and small["seeds_s"] > 0
    assert big["seeds_s"] is None and "skipped" in str(big["seeds_note"])
