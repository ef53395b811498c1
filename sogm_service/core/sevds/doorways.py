"""Doorway lines of a window: where rooms are cut although the data show no edge there.

A doorway is a gap in a wall: a run of cells that are not occupied, in one row (or column),
between two occupied runs that continue along that row (or column).  The wall's line goes on
through the gap, and that is where a person labelling rooms cuts one room from the next; the
cells on either side are the same free floor, so no data term can place a boundary there.
SEVDS's contour term rewards a supercell boundary on that line instead
(:mod:`sogm_service.core.sevds.segment`, "Doorways").

A run of ``g`` cells counts as a gap in a wall when the occupied runs at both of its ends are at
least ``g / 2`` cells long: a wall continues on both sides of its door, while the space between
two pieces of furniture, or between furniture and a wall across the room, is bounded by short
runs (the width of the object) or is longer than the objects are wide.  A cell is occupied when
any layer lies in its top probability bin (for an occupancy layer with 3 bins: ``p >= 2/3``).

The line is the gap's middle: for a horizontal wall of ``t`` rows with a door, the gap cells of
those rows form a band ``t`` cells thick, and the marked edge is the one below the band's middle
row (its upper middle row when ``t`` is even).  Numba, ``cache=True``; pure, no I/O.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from sogm_service.core.sevds.numba_cache import ensure_cache_dir

ensure_cache_dir()

import numba  # noqa: E402  (after the cache directory is chosen)

DOWN: int = 1
"""Bit of a cell's mask: the edge to the cell below lies on a doorway line."""
RIGHT: int = 2
"""Bit of a cell's mask: the edge to the cell on the right lies on a doorway line."""


@numba.njit(cache=True, nogil=True)
def _row_gaps(occ: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """Cells of the gaps in walls along the rows (module docstring)."""
    h, w = occ.shape
    gap = np.zeros((h, w), np.bool_)
    for v in range(h):
        u = 0
        prev_len = 0  # length of the occupied run that ends just before u
        while u < w:
            start = u
            kind = occ[v, u]
            while u < w and occ[v, u] == kind:
                u += 1
            if kind:
                prev_len = u - start
                continue
            if prev_len == 0 or u == w:  # not bounded by occupied cells on both ends
                prev_len = 0
                continue
            nxt = u
            while nxt < w and occ[v, nxt]:
                nxt += 1
            if 2 * min(prev_len, nxt - u) >= u - start:
                gap[v, start:u] = True
            prev_len = 0
    return gap


@numba.njit(cache=True, nogil=True)
def _middle_edges(band: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """Per column, each vertical run of band cells: True at its middle row (the upper middle
    of an even run), whose edge to the cell below is the line."""
    h, w = band.shape
    line = np.zeros((h, w), np.bool_)
    for u in range(w):
        v = 0
        while v < h:
            if not band[v, u]:
                v += 1
                continue
            start = v
            while v < h and band[v, u]:
                v += 1
            mid = start + (v - start - 1) // 2
            if mid + 1 < h:
                line[mid, u] = True
    return line


@numba.njit(cache=True, nogil=True)
def _occupied(qt: npt.NDArray[np.uint8], bins: int) -> npt.NDArray[np.bool_]:
    """Cells with any layer in the top bin, from the ``(H, W, N)`` bin indices."""
    h, w, nl = qt.shape
    occ = np.zeros((h, w), np.bool_)
    for v in range(h):
        for u in range(w):
            for n in range(nl):
                if qt[v, u, n] == bins - 1:
                    occ[v, u] = True
                    break
    return occ


def doorway_edges(qt: npt.NDArray[np.uint8], bins: int) -> npt.NDArray[np.uint8]:
    """``(H, W)`` masks of the doorway-line edges of every cell (bits :data:`DOWN` and
    :data:`RIGHT`), from the ``(H, W, N)`` bin indices of the sweeps."""
    occ = _occupied(qt, bins)
    horizontal = _middle_edges(_row_gaps(occ))  # doors in horizontal walls: edges down
    # Doors in vertical walls: the same on the transpose, where "down" is "right".
    vertical = _middle_edges(_row_gaps(np.ascontiguousarray(occ.T))).T
    return np.ascontiguousarray(horizontal * np.uint8(DOWN) | vertical * np.uint8(RIGHT))
