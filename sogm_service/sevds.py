"""SEVDS: Supercells Extracted via Variance-Driven Sampling (paper section III-D.2, Eq. 7-10).

SEVDS is SEEDS (Van den Bergh et al., ECCV 2012) with the colour-histogram term replaced by a
variance term.  The structure is SEEDS's:

1. The window is cut into square supercells of ``block_size`` cells (the paper's rule of thumb:
   the edge of the smallest object to be found, 8 cells).
2. Block-level moves, coarse to fine: the supercells are split into blocks of
   ``block_size / 2, block_size / 4, ...`` cells (``levels - 1`` block levels, each an exact
   halving; a level is dropped when ``block_size`` is not divisible).  A block on a supercell
   boundary may move to a 4-neighbouring supercell.  Each block level is swept twice
   (forward and backward raster order), as OpenCV's SEEDS with ``double_step``.
3. Cell-level moves: ``iterations`` sweeps over single cells, alternating direction.

A move must keep the losing supercell locally connected (the 3x3 simple-point test of SEEDS, on
the grid of the current level), may not empty it, and -- the paper's corner-case rule -- a
supercell whose total variance is zero may not shrink.

**State per supercell (Eq. 9-10).**  One K-bin histogram per semantic layer, ``hist[c, n, k]``
(bin ``k`` covers probabilities ``[k/K, (k+1)/K)``, the last bin includes 1), never the joint
``K**N`` histogram of Eq. 9: by Eq. 10 only the marginals matter, so memory and time are linear in
the number of layers.  The distribution term is

    ``D'(c) = sum_n var(h(c_n))``    (Eq. 10)

where ``var(h(c_n))`` is the variance of the probability distribution that the layer-n histogram
describes (bin centres ``(2k + 1) / 2K`` as in Eq. 9, weighted by the counts): 0 for a supercell
whose cells share one bin in every layer, large for contradicting probabilities.  It is evaluated
from the histogram's first two moments, kept next to it, so that a candidate move costs O(N).

**Contour term (Eq. 7).**  ``H(c) = D'(c) + gamma * G(c)`` with ``G(c) = perimeter(c) / |c|``:
the supercell's boundary length (4-neighbour edges to other supercells, the window border not
counted) per cell.  It is intensive like the variance, so ``gamma`` weighs two quantities of the
same kind; it prefers compact supercells and breaks the ties of homogeneous regions.

**Move criteria** (``criterion``):

* ``"distribution"`` -- the paper's rule: the unit ``c'`` joins the neighbouring supercell ``c``
  that gives the lowest ``H(c_hat) - H(c)`` with ``c_hat = c + c'``, if that is negative
  ("if D(c_hat) < D(c) holds, the newly c_hat will be used further", with the contour term of
  Eq. 7).  Only the receiving supercell is judged.
* ``"energy"`` -- the total-energy variant: the move must lower
  ``E = sum_c |c| H(c) = sum_c (SSE(c) + gamma * perimeter(c))``, judging the losing and the
  receiving supercell together; ``|c| D'(c)`` is the supercell's sum of squared deviations, which
  is additive over cells (plain variances of sets of different size are not).

How they behave (``sogm-service eval supercells``, :mod:`sogm_service.evaluation`): the paper's
rule never lets a zero-variance receiver grow without the contour term (``D(c_hat) < 0`` is
impossible), and because the loser is not judged a cell can go back and forth between two
supercells; the sweeps simply stop after ``iterations``.  It gives the lowest intra-cluster
variation.  The energy rule converges (every move lowers E) and follows object boundaries much
better (boundary recall, undersegmentation, explained variation) at a higher ICV.  The
zero-variance rule applies to both.

Decisions where the paper is silent: the bin of ``p`` is ``floor(p * K)`` (1 goes to the last
bin); the image border is not part of a perimeter; a block level is used only while the block
edge halves exactly (so blocks nest and are single-label when their level runs); candidates are
the supercells of the unit's 4-neighbours, the best one is taken; ties (change ``>= -1e-12``) do
not move.  Speed: the sweeps are numba kernels (``cache=True``); 256x256 cells with 3 layers run
in about 7 ms on this machine (OpenCV's SEEDS: about 9 ms), see
:func:`benchmark_sevds_vs_seeds`.

Pure numpy + numba (``cache=True``), no I/O.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numba
import numpy as np
import numpy.typing as npt

Criterion = Literal["distribution", "energy"]
CRITERIA: tuple[Criterion, ...] = ("distribution", "energy")

# Numerical noise of the running moments; a move must gain more than this.
_EPS = 1e-12


@dataclass(frozen=True, slots=True)
class SevdsParams:
    """SEVDS parameters (defaults as the ``supercells`` queryable's)."""

    block_size: int = 8
    levels: int = 3
    bins: int = 5
    iterations: int = 4
    gamma: float = 0.01
    criterion: Criterion = "distribution"

    def __post_init__(self) -> None:
        if self.block_size < 1:
            raise ValueError(f"block_size must be >= 1, got {self.block_size}")
        if self.levels < 1:
            raise ValueError(f"levels must be >= 1, got {self.levels}")
        if not 2 <= self.bins <= 255:
            raise ValueError(f"bins must lie in [2, 255], got {self.bins}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        if not (math.isfinite(self.gamma) and self.gamma >= 0):
            raise ValueError(f"gamma must be finite and >= 0, got {self.gamma}")
        if self.criterion not in CRITERIA:
            raise ValueError(f"criterion must be one of {CRITERIA}, got {self.criterion!r}")

    def block_sizes(self) -> list[int]:
        """Edge lengths of the block levels that take moves, coarse to fine (each halves)."""
        sizes: list[int] = []
        s = self.block_size
        for _ in range(self.levels - 1):
            if s % 2 or s < 4:
                break
            s //= 2
            sizes.append(s)
        return sizes


@dataclass(frozen=True, slots=True)
class SevdsResult:
    """Labels ``(H, W)`` int32 ``0..S-1`` and the final per-layer histograms ``(S, N, K)``."""

    labels: npt.NDArray[np.int32]
    histograms: npt.NDArray[np.int32]
    moves: int

    @property
    def count(self) -> int:
        return int(self.histograms.shape[0])

    def variances(self) -> npt.NDArray[np.float64]:
        """``(S, N)``: ``var(h(c_n))`` of Eq. 10 for every supercell and layer."""
        return histogram_variance(self.histograms)

    def distribution(self) -> npt.NDArray[np.float64]:
        """``(S,)``: the distribution term ``D'(c)`` of Eq. 10."""
        return self.variances().sum(axis=1)


def bin_centres(bins: int) -> npt.NDArray[np.float64]:
    """Centres ``(2k + 1) / 2K`` of the K probability bins (Eq. 9)."""
    return np.asarray((2.0 * np.arange(bins) + 1.0) / (2.0 * bins), dtype=np.float64)


def histogram_variance(hist: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Variance of the distribution each K-bin histogram describes (last axis = bins)."""
    h = np.asarray(hist, dtype=np.float64)
    x = bin_centres(h.shape[-1])
    n = h.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (h @ x) / n
        var = (h @ (x * x)) / n - mean * mean
    return np.asarray(np.where(n > 0, np.maximum(var, 0.0), 0.0), dtype=np.float64)


def _check_stack(stack: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """A C-contiguous float32 ``(N, H, W)`` stack of finite values, N, H, W >= 1."""
    p = np.ascontiguousarray(stack, dtype=np.float32)
    if p.ndim != 3 or min(p.shape) < 1:
        raise ValueError(f"expected a non-empty (N, H, W) stack, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("the stack holds NaN or infinite values")
    return p


def quantize(stack: npt.ArrayLike, bins: int) -> npt.NDArray[np.uint8]:
    """``(N, H, W)`` probabilities -> bin indices ``floor(p * K)`` clipped to ``0..K-1``."""
    p = np.asarray(stack, dtype=np.float32)
    return np.clip(np.floor(p * bins), 0, bins - 1).astype(np.uint8)


# --------------------------------------------------------------------------- numba kernels


@numba.njit(cache=True, nogil=True, inline="always")
def _layer_var(inv_c: float, m1: float, m2: float) -> float:
    """Variance from the moments of a histogram with ``1 / count = inv_c`` (no division)."""
    mean = m1 * inv_c
    return max(m2 * inv_c - mean * mean, 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _zero_variance(hist: npt.NDArray[np.int32], c: int) -> bool:
    """True when every layer histogram of supercell ``c`` has a single occupied bin."""
    for n in range(hist.shape[1]):
        used = 0
        for k in range(hist.shape[2]):
            if hist[c, n, k] > 0:
                used += 1
        if used > 1:
            return False
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _removable(ul: npt.NDArray[np.int32], i: int, j: int) -> bool:
    """SEEDS's 3x3 simple-point test: the label at (i, j) stays 4-connected without (i, j).

    Walk the 8-ring; runs of same-label cells are 4-connected inside the ring.  Removing the
    centre is safe when at most one run touches it through a 4-neighbour.
    """
    di = (-1, -1, 0, 1, 1, 1, 0, -1)
    dj = (0, 1, 1, 1, 0, -1, -1, -1)
    a = ul[i, j]
    hu, wu = ul.shape
    mask = 0  # bit r set: ring cell r carries label a (a bit mask: no allocation per call)
    for r in range(8):
        y, x = i + di[r], j + dj[r]
        if 0 <= y < hu and 0 <= x < wu and ul[y, x] == a:
            mask |= 1 << r
    if mask == 255:
        return False  # interior unit
    runs = 0
    for r in range(8):
        if mask >> r & 1 and not mask >> ((r + 7) % 8) & 1:
            # A run starts at r: does it reach a 4-neighbour (even ring index)?
            touches = False
            t = r
            while mask >> t & 1:
                touches = touches or t % 2 == 0
                t = (t + 1) % 8
            if touches:
                runs += 1
    return runs <= 1


@numba.njit(cache=True, nogil=True)
def _move_hist(q: npt.NDArray[np.uint8], hist: npt.NDArray[np.int32], s: int, i: int, j: int,
               a: int, b: int) -> None:
    """Move the cells of unit (i, j) (size ``s``) from supercell a's histograms to b's."""
    h, w = q.shape[0], q.shape[1]
    for v in range(i * s, min(h, (i + 1) * s)):
        for u in range(j * s, min(w, (j + 1) * s)):
            for n in range(q.shape[2]):
                k = q[v, u, n]
                hist[a, n, k] -= 1
                hist[b, n, k] += 1


@numba.njit(cache=True, nogil=True, inline="always")
def _dist_of(c: int, cnt: npt.NDArray[np.float64], s1: npt.NDArray[np.float64],
             s2: npt.NDArray[np.float64]) -> float:
    """Eq. 10: ``D'(c) = sum_n var(h(c_n))`` from the histogram moments of supercell c."""
    inv = 1.0 / cnt[c]
    total = 0.0
    for n in range(s1.shape[1]):
        total += _layer_var(inv, s1[c, n], s2[c, n])
    return total


@numba.njit(cache=True, nogil=True, inline="always")
def _dist_with(c: int, i: int, j: int, sign: float, cnt: npt.NDArray[np.float64],
               s1: npt.NDArray[np.float64], s2: npt.NDArray[np.float64],
               uc: npt.NDArray[np.float64], um1: npt.NDArray[np.float64],
               um2: npt.NDArray[np.float64], q: npt.NDArray[np.uint8],
               centres: npt.NDArray[np.float64], s: int) -> float:
    """Eq. 10 of supercell c with unit (i, j) added (sign +1) or removed (sign -1)."""
    inv = 1.0 / (cnt[c] + sign * _unit_count(uc, i, j, s))
    total = 0.0
    for n in range(s1.shape[1]):
        x1, x2 = _unit_moment(um1, um2, q, centres, s, i, j, n)
        total += _layer_var(inv, s1[c, n] + sign * x1, s2[c, n] + sign * x2)
    return total


@numba.njit(cache=True, nogil=True, inline="always")
def _unit_count(uc: npt.NDArray[np.float64], i: int, j: int, s: int) -> float:
    return 1.0 if s == 1 else uc[i, j]


@numba.njit(cache=True, nogil=True, inline="always")
def _unit_moment(um1: npt.NDArray[np.float64], um2: npt.NDArray[np.float64],
                 q: npt.NDArray[np.uint8], centres: npt.NDArray[np.float64], s: int, i: int,
                 j: int, n: int) -> tuple[float, float]:
    """Sums of x and x^2 of unit (i, j) in layer n.  Single cells (s == 1) read them from their
    bin index: building (H, W, N) moment arrays cost more than the sweeps (page faults)."""
    if s == 1:
        x = centres[q[i, j, n]]
        return x, x * x
    return um1[i, j, n], um2[i, j, n]


@numba.njit(cache=True, nogil=True, inline="always")
def _edges_to(b: int, nb_lab: npt.NDArray[np.int32], nb_w: npt.NDArray[np.float64]) -> float:
    """Length of the unit's border shared with supercell b."""
    e = 0.0
    for t in range(4):
        if nb_lab[t] == b:
            e += nb_w[t]
    return e


@numba.njit(cache=True, nogil=True, inline="always")
def _seen_before(nb_lab: npt.NDArray[np.int32], r: int) -> bool:
    """Whether neighbour r's label already appeared among neighbours 0..r-1."""
    for t in range(r):  # noqa: SIM110 - a plain loop: numba compiles it, not any(generator)
        if nb_lab[t] == nb_lab[r]:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _apply_move(a: int, b: int, i: int, j: int, p_unit: float, e_a: float, e_b: float,
                cnt: npt.NDArray[np.float64], s1: npt.NDArray[np.float64],
                s2: npt.NDArray[np.float64], perim: npt.NDArray[np.float64],
                dval: npt.NDArray[np.float64], hist: npt.NDArray[np.int32],
                uc: npt.NDArray[np.float64], um1: npt.NDArray[np.float64],
                um2: npt.NDArray[np.float64], q: npt.NDArray[np.uint8],
                centres: npt.NDArray[np.float64], s: int) -> None:
    """Move unit (i, j) from a to b: counts, moments, histograms, perimeters, D'."""
    perim[a] += 2.0 * e_a - p_unit
    perim[b] += p_unit - 2.0 * e_b
    u = _unit_count(uc, i, j, s)
    cnt[a] -= u
    cnt[b] += u
    for n in range(s1.shape[1]):
        x1, x2 = _unit_moment(um1, um2, q, centres, s, i, j, n)
        s1[a, n] -= x1
        s2[a, n] -= x2
        s1[b, n] += x1
        s2[b, n] += x2
    dval[a] = _dist_of(a, cnt, s1, s2)
    dval[b] = _dist_of(b, cnt, s1, s2)
    _move_hist(q, hist, s, i, j, a, b)


@numba.njit(cache=True, nogil=True)
def _sweep(ul: npt.NDArray[np.int32], uc: npt.NDArray[np.float64],
           um1: npt.NDArray[np.float64], um2: npt.NDArray[np.float64],
           rh: npt.NDArray[np.float64], cw: npt.NDArray[np.float64], q: npt.NDArray[np.uint8],
           s: int, cnt: npt.NDArray[np.float64], s1: npt.NDArray[np.float64],
           s2: npt.NDArray[np.float64], perim: npt.NDArray[np.float64],
           dval: npt.NDArray[np.float64], hist: npt.NDArray[np.int32],
           centres: npt.NDArray[np.float64], gamma: float, energy: bool, reverse: bool) -> int:
    """One raster sweep of unit moves on the unit grid ``ul`` (units of ``s`` x ``s`` cells).

    Per supercell: count, sums of x and x^2 per layer, perimeter, D' and the K-bin histograms,
    all updated in place.
    """
    hu, wu = ul.shape
    moves = 0
    nb_lab = np.empty(4, dtype=np.int32)
    nb_w = np.empty(4, dtype=np.float64)
    for ii in range(hu):
        i = hu - 1 - ii if reverse else ii
        for jj in range(wu):
            j = wu - 1 - jj if reverse else jj
            a = ul[i, j]
            p_unit, e_a = _neighbours(ul, i, j, rh, cw, nb_lab, nb_w)
            u = _unit_count(uc, i, j, s)
            if e_a == p_unit or cnt[a] <= u:
                continue  # interior unit, or the move would empty a
            # The best neighbouring supercell b to join (criteria in the module docstring).
            # Written out here, not in a helper: passing the state arrays to a function cost
            # several times the arithmetic (reference counting per call).
            lose = 0.0
            if energy:  # the loser's part of the energy change is the same for every b
                lose = (cnt[a] - u) * _dist_with(a, i, j, -1.0, cnt, s1, s2, uc, um1, um2, q,
                                                 centres, s) \
                    - cnt[a] * dval[a]
            best, b = -_EPS, -1
            for r in range(4):
                c = nb_lab[r]
                if c < 0 or c == a or _seen_before(nb_lab, r):
                    continue
                e_c = _edges_to(c, nb_lab, nb_w)
                d_new = _dist_with(c, i, j, 1.0, cnt, s1, s2, uc, um1, um2, q, centres, s)
                if energy:
                    # E = sum_c |c| H(c): |c| D'(c) is the sum of squared deviations.
                    sc = lose + (cnt[c] + u) * d_new - cnt[c] * dval[c] \
                        + gamma * 2.0 * (e_a - e_c)
                else:
                    # Paper: H(c_hat) - H(c) of the receiver; Eq. 7, G = perimeter / area.
                    g_new = (perim[c] + p_unit - 2.0 * e_c) / (cnt[c] + u)
                    sc = d_new - dval[c] + gamma * (g_new - perim[c] / cnt[c])
                if sc < best:
                    best, b = sc, c
            # The constraints come after the (cheaper, usually negative) search.  The paper's
            # corner case: a supercell of zero total variance may not shrink.
            if b < 0 or (dval[a] < 1e-9 and _zero_variance(hist, a)):
                continue
            if not _removable(ul, i, j):
                continue
            _apply_move(a, b, i, j, p_unit, e_a, _edges_to(b, nb_lab, nb_w), cnt, s1, s2,
                        perim, dval, hist, uc, um1, um2, q, centres, s)
            ul[i, j] = b
            moves += 1
    return moves


@numba.njit(cache=True, nogil=True, inline="always")
def _neighbours(ul: npt.NDArray[np.int32], i: int, j: int, rh: npt.NDArray[np.float64],
                cw: npt.NDArray[np.float64], nb_lab: npt.NDArray[np.int32],
                nb_w: npt.NDArray[np.float64]) -> tuple[float, float]:
    """Fill the 4 neighbours' labels (-1 outside) and shared edge lengths; return the unit's
    inner border length and the part of it shared with its own supercell."""
    hu, wu = ul.shape
    a = ul[i, j]
    p_unit, e_a = 0.0, 0.0
    for r in range(4):
        y = i - 1 if r == 0 else (i + 1 if r == 2 else i)
        x = j + 1 if r == 1 else (j - 1 if r == 3 else j)
        if 0 <= y < hu and 0 <= x < wu:
            nb_lab[r] = ul[y, x]
            # Shared edge length in cells: a column's width (vertical) or a row's height.
            nb_w[r] = cw[j] if r % 2 == 0 else rh[i]
            p_unit += nb_w[r]
            if nb_lab[r] == a:
                e_a += nb_w[r]
        else:
            nb_lab[r] = -1
            nb_w[r] = 0.0
    return p_unit, e_a


@numba.njit(cache=True, nogil=True)
def _unit_moments(q: npt.NDArray[np.uint8], centres: npt.NDArray[np.float64], s: int,
                  hu: int, wu: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64],
                                             npt.NDArray[np.float64]]:
    """Per unit of ``s`` x ``s`` cells: cell count and per-layer sums of x and x^2 (Eq. 9)."""
    h, w, nl = q.shape
    uc = np.zeros((hu, wu))
    m1 = np.zeros((hu, wu, nl))
    m2 = np.zeros((hu, wu, nl))
    # Loop units, then their cells: no integer division per cell (it dominated this loop).
    for i in range(hu):
        for j in range(wu):
            for v in range(i * s, min(h, (i + 1) * s)):
                for u in range(j * s, min(w, (j + 1) * s)):
                    uc[i, j] += 1.0
                    for n in range(nl):
                        x = centres[q[v, u, n]]
                        m1[i, j, n] += x
                        m2[i, j, n] += x * x
    return uc, m1, m2


# --------------------------------------------------------------------------- driver


def _initial_labels(h: int, w: int, b: int) -> npt.NDArray[np.int32]:
    """Square supercells of ``b`` x ``b`` cells in raster order."""
    cols = -(-w // b)
    rows = (np.arange(h, dtype=np.int32) // b) * cols
    return np.ascontiguousarray(rows[:, None] + (np.arange(w, dtype=np.int32) // b)[None, :])


def _perimeters(labels: npt.NDArray[np.int32], count: int) -> npt.NDArray[np.float64]:
    """Boundary length of every supercell: 4-neighbour edges to another label."""
    perim = np.zeros(count)
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        diff = a != b
        perim += np.bincount(a[diff], minlength=count) + np.bincount(b[diff], minlength=count)
    return perim


@numba.njit(cache=True, nogil=True)
def _quantize_hwn(p: npt.NDArray[np.float32], bins: int) -> npt.NDArray[np.uint8]:
    """``(N, H, W)`` probabilities -> ``(H, W, N)`` bin indices (cell-major for the sweeps)."""
    nl, h, w = p.shape
    out = np.empty((h, w, nl), np.uint8)
    for n in range(nl):
        for v in range(h):
            for u in range(w):
                k = int(p[n, v, u] * bins)
                out[v, u, n] = min(max(k, 0), bins - 1)
    return out


@numba.njit(cache=True, nogil=True)
def _supercell_state(
    qt: npt.NDArray[np.uint8], labels: npt.NDArray[np.int32], count: int,
    centres: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64],
           npt.NDArray[np.int32]]:
    """Count, moments (sums of x, x^2) and per-layer histograms ``(S, N, K)`` per supercell."""
    h, w, nl = qt.shape
    hist = np.zeros((count, nl, centres.size), np.int32)
    cnt = np.zeros(count)
    for v in range(h):
        for u in range(w):
            c = labels[v, u]
            cnt[c] += 1.0
            for n in range(nl):
                hist[c, n, qt[v, u, n]] += 1
    s1 = np.zeros((count, nl))
    s2 = np.zeros((count, nl))
    for c in range(count):
        for n in range(nl):
            for k in range(centres.size):
                s1[c, n] += hist[c, n, k] * centres[k]
                s2[c, n] += hist[c, n, k] * centres[k] * centres[k]
    return cnt, s1, s2, hist


def sevds(stack: npt.ArrayLike, params: SevdsParams | None = None) -> SevdsResult:
    """Segment an ``(N, H, W)`` probability stack into supercells (Eq. 7-10).

    Returns the label image and the final per-layer histograms.  Every supercell stays non-empty
    and (by the local connectivity test of SEEDS) connected; labels are ``0..S-1`` in the raster
    order of the initial grid.
    """
    p = params or SevdsParams()
    prob = _check_stack(stack)
    _, h, w = prob.shape
    qt = _quantize_hwn(prob, p.bins)
    labels = _initial_labels(h, w, p.block_size)
    count = int(labels.max()) + 1
    centres = bin_centres(p.bins)
    cnt, s1, s2, hist = _supercell_state(qt, labels, count, centres)
    perim = _perimeters(labels, count)
    dval = histogram_variance(hist).sum(axis=1)
    energy = p.criterion == "energy"
    moves = 0
    schedule = [(s, 2) for s in p.block_sizes()] + [(1, p.iterations)]
    for s, sweeps in schedule:
        hu, wu = -(-h // s), -(-w // s)
        ul = np.ascontiguousarray(labels[::s, ::s])  # blocks nest: each is one label
        if s > 1:
            uc, m1, m2 = _unit_moments(qt, centres, s, hu, wu)
        else:  # single cells take their moments from their bin index (_unit_moment)
            uc, m1, m2 = np.ones((1, 1)), np.zeros((1, 1, 1)), np.zeros((1, 1, 1))
        rh = np.minimum(s, h - s * np.arange(hu)).astype(np.float64)
        cw = np.minimum(s, w - s * np.arange(wu)).astype(np.float64)
        for sweep in range(sweeps):
            moves += _sweep(ul, uc, m1, m2, rh, cw, qt, s, cnt, s1, s2, perim, dval, hist,
                            centres, float(p.gamma), energy, sweep % 2 == 1)
        labels = np.repeat(np.repeat(ul, s, axis=0), s, axis=1)[:h, :w]
    return SevdsResult(np.ascontiguousarray(labels, dtype=np.int32), hist, moves)


# --------------------------------------------------------------------------- benchmark


def synthetic_stack(layers: int, height: int = 256, width: int = 256,
                    seed: int = 0) -> npt.NDArray[np.float32]:
    """A benchmark input: ``layers`` smooth random probability fields with sharp blobs."""
    rng = np.random.default_rng(seed)
    small = rng.random((layers, max(1, height // 16), max(1, width // 16)))
    out = np.empty((layers, height, width), np.float32)
    for n in range(layers):
        field = cv2.resize(small[n], (width, height), interpolation=cv2.INTER_CUBIC)
        # Sharpen into object-like regions, then add sensor noise.
        out[n] = 1.0 / (1.0 + np.exp(-12.0 * (field - 0.5)))
    out += rng.normal(0.0, 0.05, out.shape).astype(np.float32)
    return np.clip(out, 0.0, 1.0)


def seeds_histogram_bytes(height: int, width: int, layers: int, bins: int, levels: int,
                          num_superpixels: int) -> int:
    """Rough memory of OpenCV SEEDS's joint ``bins**layers`` block histograms (float32)."""
    block = max(1, int(math.sqrt(height * width / max(1, num_superpixels))))
    total = 0
    for level in range(levels):
        size = max(1, block >> (levels - 1 - level))
        total += -(-height // size) * -(-width // size)
    return total * bins**layers * 4


def _best_time(fn: Callable[[], object], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _seeds_run(img: npt.NDArray[np.uint8], count: int, levels: int, bins: int,
               iterations: int) -> int:
    h, w, c = img.shape
    seeds = cv2.ximgproc.createSuperpixelSEEDS(w, h, c, count, levels, 2, bins, False)
    seeds.iterate(img, iterations)
    return int(seeds.getNumberOfSuperpixels())


def benchmark_sevds_vs_seeds(
    layers: tuple[int, ...] = (3, 8, 16),
    *,
    height: int = 256,
    width: int = 256,
    params: SevdsParams | None = None,
    repeats: int = 5,
    seeds_memory_limit: int = 1 << 30,
    seed: int = 0,
) -> list[dict[str, float | int | str | None]]:
    """Time SEVDS against OpenCV's SEEDS on the same input and superpixel count.

    For every layer count: best-of-``repeats`` wall time (s) of one whole SEVDS call and of one
    SEEDS create + iterate (same levels, bins, iterations; prior 2), after a warm-up run (numba
    compilation is not timed).  SEEDS is skipped (``seeds_s = None``, ``seeds_note`` says why)
    when its joint histograms would exceed ``seeds_memory_limit`` bytes.  No printing.
    """
    p = params or SevdsParams()
    rows: list[dict[str, float | int | str | None]] = []
    for n in layers:
        stack = synthetic_stack(n, height, width, seed)
        sevds(stack, p)  # warm-up: numba compile / cache load
        sevds_s = _best_time(lambda s=stack: sevds(s, p), repeats)  # type: ignore[misc]
        count = sevds(stack, p).count
        row: dict[str, float | int | str | None] = {
            "layers": n, "height": height, "width": width, "supercells": count,
            "sevds_s": sevds_s, "seeds_s": None, "seeds_superpixels": None, "seeds_note": "",
            "ratio_sevds_over_seeds": None}
        need = seeds_histogram_bytes(height, width, n, p.bins, p.levels, count)
        if need > seeds_memory_limit:
            row["seeds_note"] = f"skipped: joint histograms need ~{need / 2**30:.1f} GiB"
        else:
            img = np.ascontiguousarray(np.rint(stack.transpose(1, 2, 0) * 255).astype(np.uint8))
            row["seeds_superpixels"] = _seeds_run(img, count, p.levels, p.bins, p.iterations)
            seeds_s = _best_time(
                lambda i=img, c=count: _seeds_run(  # type: ignore[misc]
                    i, c, p.levels, p.bins, p.iterations), repeats)
            row["seeds_s"] = seeds_s
            row["ratio_sevds_over_seeds"] = sevds_s / seeds_s
        rows.append(row)
    return rows
