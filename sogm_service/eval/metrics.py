"""Segmentation metrics of the paper's evaluation (section IV), generalised to N-layer grids.

All metrics follow Stutz et al., "Superpixels: An evaluation of the state-of-the-art" (CVIU 2018),
the benchmark the paper cites for its tuning rule ``(1 - BR) + UE``; the image ``I`` there is a
colour image, here it is an ``(N, H, W)`` stack of occupancy probabilities (a cell's "colour" is
its vector of N layer probabilities, distances are Euclidean over the layers).

* :func:`pureness` - the paper's Eq. 12: mean over superpixels of the fraction of its cells that
  carry its majority ground-truth class.
* :func:`intra_cluster_variation` - ICV (Benesova & Kottman):
  ``1/|S| sum_j sqrt(sum_{x in S_j} ||I(x) - mu_j||^2) / |S_j|``.
* :func:`explained_variation` - EV (Moore et al.):
  ``sum_j |S_j| ||mu_j - mu||^2 / sum_x ||I(x) - mu||^2``.
* :func:`undersegmentation_error` - UE in the Neubert & Protzel form:
  ``1/N sum_i sum_{j: S_j meets G_i} min(|S_j & G_i|, |S_j - G_i|)``.
* :func:`boundary_recall` - BR: the fraction of ground-truth boundary cells that have a superpixel
  boundary cell within a ``(2r+1) x (2r+1)`` square, ``r = round(0.0025 * diagonal)``.

A cell is a boundary cell when its right or lower 4-neighbour carries a different label (Stutz's
convention: a boundary is marked once, on its upper/left side).  Label images are integer arrays
of shape ``(H, W)``; labels need not be contiguous.  Pure numpy/OpenCV, no I/O.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

METRICS: tuple[str, ...] = ("pureness", "icv", "ev", "ue", "br")
METRIC_TITLES: dict[str, str] = {
    "pureness": "Pureness (Eq. 12, higher is better)",
    "icv": "Intra-Cluster Variation (lower is better)",
    "ev": "Explained Variation (higher is better)",
    "ue": "Undersegmentation Error (lower is better)",
    "br": "Boundary Recall (higher is better)",
}



def _dense(labels: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], int]:
    """Relabel to ``0..k-1`` (labels may be sparse or negative); return the map and ``k``."""
    flat = np.asarray(labels).ravel()
    uniq, inv = np.unique(flat, return_inverse=True)
    return inv.astype(np.int64), int(uniq.size)


def _check_same_shape(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"label images differ in shape: {a.shape} vs {b.shape}")


def contingency(superpixels: npt.ArrayLike, ground_truth: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """``(|S|, |G|)`` table of ``|S_j & G_i|`` over dense relabelings of both images."""
    sp, gt = np.asarray(superpixels), np.asarray(ground_truth)
    _check_same_shape(sp, gt)
    s, ns = _dense(sp)
    g, ng = _dense(gt)
    return np.bincount(s * ng + g, minlength=ns * ng).reshape(ns, ng)


def pureness(superpixels: npt.ArrayLike, classes: npt.ArrayLike) -> float:
    """Eq. 12: the average over superpixels of the share of their majority ground-truth class."""
    table = contingency(superpixels, classes)
    return float(np.mean(table.max(axis=1) / table.sum(axis=1)))


def _as_stack(image: npt.ArrayLike, shape: tuple[int, ...]) -> npt.NDArray[np.float64]:
    """``(N, H, W)`` float64 view of a one-layer ``(H, W)`` or N-layer stack."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[None]
    if img.shape[1:] != shape:
        raise ValueError(f"image {img.shape[1:]} does not match labels {shape}")
    return img.reshape(img.shape[0], -1)


def _segment_moments(
    superpixels: npt.ArrayLike, image: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64],
           npt.NDArray[np.int64]]:
    """Per segment size ``(S,)`` and layer means ``(N, S)``; the flat stack and dense labels."""
    sp = np.asarray(superpixels)
    x = _as_stack(image, sp.shape)
    s, ns = _dense(sp)
    size = np.bincount(s, minlength=ns).astype(np.float64)
    sums = np.stack([np.bincount(s, weights=layer, minlength=ns) for layer in x])
    mean = sums / size
    return size, mean, x, s


def intra_cluster_variation(superpixels: npt.ArrayLike, image: npt.ArrayLike) -> float:
    """ICV = ``1/|S| sum_j sqrt(sum_{x in S_j} ||I(x) - mu_j||^2) / |S_j|`` (lower is better)."""
    size, mean, x, s = _segment_moments(superpixels, image)
    # Sum of squared deviations per segment, over all layers: exact two-pass (no cancellation).
    dev = x - mean[:, s]
    sq = np.bincount(s, weights=np.sum(dev * dev, axis=0), minlength=size.size)
    return float(np.mean(np.sqrt(sq) / size))


def explained_variation(superpixels: npt.ArrayLike, image: npt.ArrayLike) -> float:
    """EV = ``sum_j |S_j| ||mu_j - mu||^2 / sum_x ||I(x) - mu||^2`` (higher is better).

    A constant image has no variation to explain: EV is 1 then by convention.
    """
    size, mean, x, _ = _segment_moments(superpixels, image)
    mu = x.mean(axis=1, keepdims=True)
    total = float(np.sum((x - mu) ** 2))
    if total == 0.0:
        return 1.0
    explained = float(np.sum(size * np.sum((mean - mu) ** 2, axis=0)))
    return explained / total


def undersegmentation_error(superpixels: npt.ArrayLike, ground_truth: npt.ArrayLike) -> float:
    """UE (Neubert & Protzel): the leak of superpixels across ground-truth segments, per cell."""
    table = contingency(superpixels, ground_truth)
    size = table.sum(axis=1, keepdims=True)
    leak = np.minimum(table, size - table)
    return float(leak[table > 0].sum() / table.sum())


def boundary_map(labels: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Cells whose right or lower neighbour has another label (one-sided, as Stutz et al.)."""
    lab = np.asarray(labels)
    out = np.zeros(lab.shape, dtype=bool)
    out[:, :-1] |= lab[:, :-1] != lab[:, 1:]
    out[:-1, :] |= lab[:-1, :] != lab[1:, :]
    return out


def boundary_tolerance(shape: tuple[int, int], fraction: float = 0.0025) -> int:
    """Stutz et al.'s tolerance ``r = round(fraction * image diagonal)`` in cells."""
    return round(fraction * float(np.hypot(shape[0], shape[1])))


def boundary_recall(
    superpixels: npt.ArrayLike, ground_truth: npt.ArrayLike, r: int | None = None
) -> float:
    """BR = TP / (TP + FN) over ground-truth boundary cells, square window of radius ``r``.

    ``r`` defaults to :func:`boundary_tolerance`.  Without ground-truth boundaries BR is 1.
    """
    sp, gt = np.asarray(superpixels), np.asarray(ground_truth)
    _check_same_shape(sp, gt)
    radius = boundary_tolerance(sp.shape) if r is None else int(r)
    gt_b = boundary_map(gt)
    n_gt = int(gt_b.sum())
    if n_gt == 0:
        return 1.0
    sp_b = boundary_map(sp).astype(np.uint8)
    if radius > 0:
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        sp_b = np.asarray(cv2.dilate(sp_b, kernel), dtype=np.uint8)
    return float(np.count_nonzero(gt_b & (sp_b > 0)) / n_gt)


def all_metrics(
    superpixels: npt.ArrayLike,
    image: npt.ArrayLike,
    classes: npt.ArrayLike,
    segments: npt.ArrayLike | None = None,
) -> dict[str, float]:
    """The five metrics of the paper's Fig. 12-16 in one dict.

    ``classes`` is the ground-truth class image (for Pureness); ``segments`` the ground-truth
    segmentation for UE and BR (defaults to ``classes``).
    """
    seg = classes if segments is None else segments
    return {
        "pureness": pureness(superpixels, classes),
        "icv": intra_cluster_variation(superpixels, image),
        "ev": explained_variation(superpixels, image),
        "ue": undersegmentation_error(superpixels, seg),
        "br": boundary_recall(superpixels, seg),
    }
