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
supercell whose total variance is zero may not shrink, except by a cell that puts a boundary on
a doorway line (below).

**Compact and connected.**  The simple-point test keeps every supercell one 4-connected region
(it starts as one square, and no move splits it).  The extent bound keeps it compact: a unit
may join supercell c only inside c's box, its initial block grown by ``margin =
(extent - 1) * block_size / 2`` cells on every side, so a supercell spans at most
``extent * block_size`` cells in x and in y (default ``extent`` 4: a block and a half of
reach each way).  Without the bound a run of cells of one bin (a one-cell wall) is absorbed
cell by cell along its length by whichever supercell reaches it first, and one supercell rings
a whole room; with it a wall is cut into pieces of at most ``extent`` blocks.  The bound costs
boundary recall where long supercells had traced an object's outline: on the table-top scenes
at 16-cell blocks 0.90 at ``extent`` 3, 0.93 at 4 and 0.98 unbounded (SEEDS 0.93, with a tenth
fewer superpixels); 4 keeps the room maps' undersegmentation at SEEDS's
(``sogm-service eval supercells``).

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

**Doorways.**  A person labelling rooms cuts one room from the next in the doorway, on the
line of the wall; on both sides of that line lies the same free floor, so neither the variance
nor the contour term sees an edge there, and the supercells that straddle a doorway keep
whatever boundary the initial grid gave them (on the room maps 3 in 10 doorway cells had no
boundary within BR's tolerance, for SEVDS and for SEEDS alike: a matter of where the grid
lines fell).  :mod:`sogm_service.core.sevds.doorways` finds the lines (a gap of free cells in a
row or column between two occupied runs at least half the gap long: a wall that continues on
both sides) and the cell-level sweeps count ``doorway_weight`` of energy for every line edge
inside a supercell: ``doorway`` (default 0.25) times ``(1 / bins)**2``, the squared deviation of
a cell one bin off its supercell's mean.  That is more than the contour term of the one-cell
step a boundary takes along the line (``4 gamma``), and less than adding a cell one bin off to a
homogeneous supercell costs (``|c| / (|c| + 1)`` of it, at least half), so the data decide
where they show an edge.  The supercells that straddle the line are
homogeneous floor, so the zero-variance rule would hold them; a move that cuts a line edge is
the one exception it makes.  Both parts are needed: the term alone, with the rule intact, left
BR where it was (the worst of five sets of room maps 0.0009 below SEEDS's), and dropping the
rule alone lowered it (0.0017 below).  With both, the doorway cells missed fell from 30 % to
6 % at 8-cell blocks (SEEDS 30 %), and BR lies 0.006-0.008 above SEEDS's at 8-cell blocks and
0.004-0.014 at 16 on ten sets of four room maps (UE 0.68-1.10x SEEDS's); on the table-top
scenes (:mod:`sogm_service.eval.segmentation`) it changes BR by -0.0014 to +0.0016.
``doorway = 0`` gives the segmentation without the term (and the zero-variance rule without
its exception).

**Move criteria** (``criterion``):

* ``"distribution"`` -- the paper's rule: the unit ``c'`` joins the neighbouring supercell ``c``
  that gives the lowest ``H(c_hat) - H(c)`` with ``c_hat = c + c'``, if that is negative
  ("if D(c_hat) < D(c) holds, the newly c_hat will be used further", with the contour term of
  Eq. 7).  Only the receiving supercell is judged.
* ``"energy"`` -- the total-energy variant: the move must lower
  ``E = sum_c |c| H(c) = sum_c (SSE(c) + gamma * perimeter(c))``, judging the losing and the
  receiving supercell together; ``|c| D'(c)`` is the supercell's sum of squared deviations, which
  is additive over cells (plain variances of sets of different size are not).

How they behave (``sogm-service eval supercells``, :mod:`sogm_service.eval.segmentation` and
:mod:`sogm_service.eval.roomeval`): the paper's rule never lets a zero-variance receiver grow
without the contour term (``D(c_hat) < 0`` is impossible), and because the loser is not judged
a cell can go back and forth between two supercells; the sweeps simply stop after
``iterations``.  It gives the lowest intra-cluster variation, but on an occupancy map of rooms
(walls and free floor, each one bin) it hardly moves off the grid: its undersegmentation error
is 5-9x SEEDS's.  The energy rule converges (every move lowers E) and follows boundaries: on
those maps it matches SEEDS's undersegmentation (0.95x and 0.78x at 8- and 16-cell blocks, maps
0-3) and, with the doorway term, beats its boundary recall (0.9981 against 0.9898 and 0.9941
against 0.9830; without the term 0.9893 and 0.9848, a tie).  It is therefore
the default, with the extent bound for compactness, ``bins`` 3 (free, unknown and occupied
each one bin: sensor noise of a few hundredths then leaves cells in their bin, where 5 bins
split a noisy floor and doubled the error), ``levels`` 4 and a light contour term, ``gamma``
0.001 (it smooths noisy borders; larger values fight the one-cell pieces a thin wall needs:
the error grows to 1.0-1.4x SEEDS's at 0.01 and 2-5x at 0.05 with 5 bins).  The zero-variance
rule applies to both.

Decisions where the paper is silent: the bin of ``p`` is ``floor(p * K)`` (1 goes to the last
bin); the image border is not part of a perimeter; a block level is used only while the block
edge halves exactly (so blocks nest and are single-label when their level runs); candidates are
the supercells of the unit's 4-neighbours, the best one is taken; ties (change ``>= -1e-12``) do
not move; the extent bound is checked on the receiver only (a supercell that loses a unit
stays inside its box).  Speed: the whole schedule is one numba kernel (``cache=True``), see
``sogm-service bench sevds`` and the timing columns of ``sogm-service eval supercells``.

The numba kernels live in :mod:`sogm_service.core.sevds.kernels` and are imported on the first
call, so this module (the parameters and their bounds) loads without numba.  Pure, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

Criterion = Literal["distribution", "energy"]
CRITERIA: tuple[Criterion, ...] = ("distribution", "energy")



BOUNDS: Final[dict[str, tuple[int, int]]] = {
    "block_size": (2, 64), "levels": (1, 6), "bins": (2, 64), "iterations": (1, 50),
}
"""Inclusive ranges of the integer parameters: the kernel's valid range and what a
``supercells`` query may ask for (its cost grows with each), one source for both."""
EXTENT_BOUNDS: Final[tuple[float, float]] = (1.0, 64.0)
"""Inclusive range of ``extent``: the most a supercell may span, in block sizes."""


@dataclass(frozen=True, slots=True)
class SevdsParams:
    """SEVDS parameters; these defaults are the ``supercells`` queryable's and the CLI's."""

    block_size: int = 8
    levels: int = 4
    bins: int = 3
    iterations: int = 4
    gamma: float = 0.001
    criterion: Criterion = "energy"
    extent: float = 4.0
    doorway: float = 0.25

    @property
    def doorway_weight(self) -> float:
        """Energy of one doorway-line edge inside a supercell: ``doorway`` times the squared
        deviation of a cell one bin from its supercell's mean, ``(1 / bins)**2``."""
        return self.doorway / (self.bins * self.bins)

    @property
    def margin(self) -> int:
        """Cells a supercell may reach beyond its initial block on each side (the extent
        bound: at most ``extent * block_size`` cells across, rounded down to whole cells)."""
        return int((self.extent - 1.0) * self.block_size) // 2

    def __post_init__(self) -> None:
        for name, (lo, hi) in BOUNDS.items():
            value = getattr(self, name)
            if not lo <= value <= hi:
                raise ValueError(f"{name} must lie in [{lo}, {hi}], got {value}")
        if not (math.isfinite(self.gamma) and self.gamma >= 0):
            raise ValueError(f"gamma must be finite and >= 0, got {self.gamma}")
        if not (math.isfinite(self.extent) and EXTENT_BOUNDS[0] <= self.extent
                <= EXTENT_BOUNDS[1]):
            raise ValueError(f"extent must lie in {list(EXTENT_BOUNDS)}, got {self.extent}")
        if not (math.isfinite(self.doorway) and 0.0 <= self.doorway <= 1.0):
            raise ValueError(f"doorway must lie in [0, 1], got {self.doorway}")
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



def _initial_labels(h: int, w: int, b: int) -> npt.NDArray[np.int32]:
    """Square supercells of ``b`` x ``b`` cells in raster order."""
    cols = -(-w // b)
    rows = (np.arange(h, dtype=np.int32) // b) * cols
    return np.ascontiguousarray(rows[:, None] + (np.arange(w, dtype=np.int32) // b)[None, :])



def sevds(stack: npt.ArrayLike, params: SevdsParams | None = None) -> SevdsResult:
    """Segment an ``(N, H, W)`` probability stack into supercells (Eq. 7-10).

    Returns the label image and the final per-layer histograms.  Every supercell stays non-empty
    and (by the local connectivity test of SEEDS) connected; labels are ``0..S-1`` in the raster
    order of the initial grid.
    """
    p = params or SevdsParams()
    prob = _check_stack(stack)
    _, h, w = prob.shape
    from sogm_service.core.sevds import kernels as k  # numba: compiled or loaded on first use

    qt = k.quantize_hwn(prob, p.bins)
    labels = _initial_labels(h, w, p.block_size)
    count = int(labels.max()) + 1
    centres = bin_centres(p.bins)
    cnt, s1, s2, hist, perim = k.supercell_state(qt, labels, count, centres)
    dval = histogram_variance(hist).sum(axis=1)
    sizes = np.array([*p.block_sizes(), 1], np.int64)
    sweeps = np.array([2] * (sizes.size - 1) + [p.iterations], np.int64)
    if p.doorway > 0.0:
        from sogm_service.core.sevds.doorways import doorway_edges

        door = doorway_edges(qt, p.bins)
    else:
        door = np.zeros((h, w), np.uint8)
    labels, moves = k.run(qt, labels, sizes, sweeps, cnt, s1, s2, perim, dval, hist, centres,
                         float(p.gamma), p.criterion == "energy", p.block_size, p.margin,
                         door, p.doorway_weight)
    return SevdsResult(np.ascontiguousarray(labels, dtype=np.int32), hist, int(moves))



def warm_up() -> None:
    """Compile (or load from numba's cache) every SEVDS kernel with the argument types the
    server's queries use: one small segmentation of each criterion."""
    rng = np.random.default_rng(0)
    stack = rng.random((2, 32, 32), dtype=np.float32)
    for criterion in CRITERIA:
        sevds(stack, SevdsParams(criterion=criterion))
