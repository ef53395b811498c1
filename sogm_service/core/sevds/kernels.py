"""The numba kernels of SEVDS (:mod:`sogm_service.core.sevds.segment`): the block and pixel sweeps.

Kept apart from the public function so that importing the parameters does not load numba.
Every kernel is ``cache=True``; :mod:`sogm_service.core.sevds.numba_cache` picks where the cache
lives (a writable directory even in a read-only install) before numba is imported, and the
server compiles them in the background at start (:func:`sogm_service.core.sevds.segment.warm_up`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from sogm_service.core.sevds.numba_cache import ensure_cache_dir

ensure_cache_dir()

import numba  # noqa: E402  (after the cache directory is chosen)

# Numerical noise of the running moments; a move must gain more than this.
_EPS = 1e-12

# --------------------------------------------------------------------------- numba kernels
#
# The per-unit loop of the sweep calls no non-inlined function with array arguments: numba
# increfs and decrefs each array argument with an atomic instruction, and with a dozen state
# arrays per move that cost more than the arithmetic (a fifth of the run time before the move
# was written out in the sweep).  Even an ``inline="always"`` helper can keep the pair for an
# array it is given (seen for the label grid, ~5 %), so the simple-point test is written out too.


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


def _removable_table() -> npt.NDArray[np.bool_]:
    """SEEDS's 3x3 simple-point test for every 8-ring pattern (bit r: ring cell r, clockwise
    from the top, carries the centre's label): True when the label stays 4-connected without
    the centre.

    Runs of same-label cells are 4-connected inside the ring; removing the centre is safe when
    at most one run touches it through a 4-neighbour (even ring index).  A full ring (255) is an
    interior unit: not removable.
    """
    table = np.zeros(256, np.bool_)
    for mask in range(255):
        runs = 0
        for r in range(8):
            if mask >> r & 1 and not mask >> ((r + 7) % 8) & 1:  # a run starts at r
                touches, t = False, r
                while mask >> t & 1:
                    touches = touches or t % 2 == 0
                    t = (t + 1) % 8
                runs += touches
        table[mask] = runs <= 1
    return table


# A global array: numba freezes it into the compiled kernels as a constant.
_REMOVABLE = _removable_table()


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


# error_model="numpy": no ZeroDivisionError check per float division (a compare and a branch
# each).  No divisor here can be 0: counts are whole numbers >= 1 (a move never empties its
# loser, and 1 / (|a| - u) is only taken when |a| > u), so the results are the same.
@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sweep(ul: npt.NDArray[np.int32], uc: npt.NDArray[np.float64],
           um1: npt.NDArray[np.float64], um2: npt.NDArray[np.float64],
           rh: npt.NDArray[np.float64], cw: npt.NDArray[np.float64], q: npt.NDArray[np.uint8],
           s: int, cnt: npt.NDArray[np.float64], s1: npt.NDArray[np.float64],
           s2: npt.NDArray[np.float64], perim: npt.NDArray[np.float64],
           dval: npt.NDArray[np.float64], hist: npt.NDArray[np.int32],
           centres: npt.NDArray[np.float64], gamma: float, energy: bool, reverse: bool,
           cols: int, block: int, margin: int, door: npt.NDArray[np.uint8],
           w_door: float) -> int:
    """One raster sweep of unit moves on the unit grid ``ul`` (units of ``s`` x ``s`` cells).

    A unit may join supercell c only inside c's box: its initial ``block`` x ``block`` square
    (row ``c // cols``, column ``c % cols`` of the initial grid) grown by ``margin`` cells on
    every side, so no supercell ever spans more than ``block + 2 margin`` cells either way.

    At the cell level (``s == 1``) every doorway-line edge (``door``: bit 1 the edge down, bit 2
    the edge right, :mod:`sogm_service.core.sevds.doorways`) inside a supercell adds ``w_door``
    to the energy, so a move that puts a boundary on the line gains ``w_door`` per edge.

    Per supercell: count, sums of x and x^2 per layer, perimeter, D' and the K-bin histograms,
    all updated in place.  Single cells (``s == 1``) take their moments from their bin index
    (``um1``/``um2`` are unused then): building (H, W, N) moment arrays cost more than the sweeps.
    """
    hu, wu = ul.shape
    h, w, nl = q.shape
    moves = 0
    nb_lab = np.empty(4, dtype=np.int32)
    nb_w = np.empty(4, dtype=np.float64)
    nb_door = np.zeros(4, dtype=np.float64)  # 1.0 where the edge to neighbour r is a doorway's
    doors = s == 1 and w_door > 0.0
    x1 = np.empty(nl)  # the unit's sums of x and x^2 per layer
    x2 = np.empty(nl)
    for ii in range(hu):
        i = hu - 1 - ii if reverse else ii
        for jj in range(wu):
            j = wu - 1 - jj if reverse else jj
            a = ul[i, j]
            # The 4 neighbours (up, right, down, left; -1 outside) and the shared edge lengths
            # in cells (a column's width or a row's height); the unit's inner border p_unit and
            # the part of it shared with its own supercell, e_a.  Edge lengths are whole
            # numbers, so these sums are exact in any order.
            if 0 < i < hu - 1 and 0 < j < wu - 1:  # all 4 neighbours inside (most units)
                l0, l1, l2, l3 = ul[i - 1, j], ul[i, j + 1], ul[i + 1, j], ul[i, j - 1]
                if l0 == a and l1 == a and l2 == a and l3 == a:
                    continue  # interior unit (checked before any other work)
                wv, wh = cw[j], rh[i]
                nb_lab[0], nb_lab[1], nb_lab[2], nb_lab[3] = l0, l1, l2, l3
                nb_w[0], nb_w[1], nb_w[2], nb_w[3] = wv, wh, wv, wh
                p_unit = 2.0 * (wv + wh)
                e_a = wv * ((l0 == a) + (l2 == a)) + wh * ((l1 == a) + (l3 == a))
            else:
                p_unit, e_a = 0.0, 0.0
                for r in range(4):
                    y = i - 1 if r == 0 else (i + 1 if r == 2 else i)
                    x = j + 1 if r == 1 else (j - 1 if r == 3 else j)
                    if 0 <= y < hu and 0 <= x < wu:
                        c = ul[y, x]
                        wt = cw[j] if r % 2 == 0 else rh[i]
                        nb_lab[r] = c
                        nb_w[r] = wt
                        p_unit += wt
                        if c == a:
                            e_a += wt
                    else:
                        nb_lab[r] = -1
                        nb_w[r] = 0.0
            u = 1.0 if s == 1 else uc[i, j]
            if e_a == p_unit or cnt[a] <= u:
                continue  # interior unit, or the move would empty a
            for n in range(nl):
                if s == 1:
                    xv = centres[q[i, j, n]]
                    x1[n] = xv
                    x2[n] = xv * xv
                else:
                    x1[n] = um1[i, j, n]
                    x2[n] = um2[i, j, n]
            # The best neighbouring supercell b to join (criteria in the module docstring).
            # d_a and d_b are D' of a without and b with the unit: after the move they are
            # exactly what D' recomputed from the updated moments gives (same operations on
            # the same values), so the move stores them instead of recomputing.
            d_a, lose, door_a = 0.0, 0.0, 0.0
            if doors:  # doorway edges up, right, down, left; door_a: those kept inside a
                nb_door[0] = 1.0 if i > 0 and (door[i - 1, j] & 1) != 0 else 0.0
                nb_door[1] = 1.0 if (door[i, j] & 2) != 0 else 0.0
                nb_door[2] = 1.0 if (door[i, j] & 1) != 0 else 0.0
                nb_door[3] = 1.0 if j > 0 and (door[i, j - 1] & 2) != 0 else 0.0
                for r in range(4):
                    if nb_lab[r] == a:
                        door_a += nb_door[r]
            if energy:  # the loser's part of the energy change is the same for every b
                inv = 1.0 / (cnt[a] - u)
                for n in range(nl):
                    d_a += _layer_var(inv, s1[a, n] - x1[n], s2[a, n] - x2[n])
                lose = (cnt[a] - u) * d_a - cnt[a] * dval[a]
            best, b, d_b = -_EPS, -1, 0.0
            for r in range(4):
                c = nb_lab[r]
                if c < 0 or c == a or _seen_before(nb_lab, r):
                    continue
                cr = c // cols  # the extent bound: the unit must lie inside c's box
                cc = c - cr * cols
                if i * s < cr * block - margin or (i + 1) * s > (cr + 1) * block + margin \
                        or j * s < cc * block - margin or (j + 1) * s > (cc + 1) * block + margin:
                    continue
                e_c = _edges_to(c, nb_lab, nb_w)
                inv = 1.0 / (cnt[c] + u)
                d_new = 0.0
                for n in range(nl):
                    d_new += _layer_var(inv, s1[c, n] + x1[n], s2[c, n] + x2[n])
                if energy:
                    # E = sum_c |c| H(c): |c| D'(c) is the sum of squared deviations.
                    sc = lose + (cnt[c] + u) * d_new - cnt[c] * dval[c] \
                        + gamma * 2.0 * (e_a - e_c)
                else:
                    # Paper: H(c_hat) - H(c) of the receiver; Eq. 7, G = perimeter / area.
                    g_new = (perim[c] + p_unit - 2.0 * e_c) / (cnt[c] + u)
                    sc = d_new - dval[c] + gamma * (g_new - perim[c] / cnt[c])
                if doors:  # doorway edges inside c after the move, less those inside a now
                    for r2 in range(4):
                        if nb_lab[r2] == c:
                            sc += w_door * nb_door[r2]
                    sc -= w_door * door_a
                if sc < best:
                    best, b, d_b = sc, c, d_new
            # The constraints come after the (cheaper, usually negative) search.  The paper's
            # corner case, for its receiver-only rule: a supercell of zero total variance may
            # not shrink (the energy rule judges the loser itself).
            if b < 0 or (door_a == 0.0 and dval[a] < 1e-9 and _zero_variance(hist, a)):
                continue
            # SEEDS's simple-point test: the 8-ring pattern of a's label, clockwise from the
            # top, looked up in _REMOVABLE.  Written out, not a helper taking ``ul``: an
            # inlined helper still increfs and decrefs its array argument (atomics, ~5 %).
            if 0 < i < hu - 1 and 0 < j < wu - 1:  # no bounds checks (almost every unit)
                mask = (int(ul[i - 1, j] == a) | int(ul[i - 1, j + 1] == a) << 1
                        | int(ul[i, j + 1] == a) << 2 | int(ul[i + 1, j + 1] == a) << 3
                        | int(ul[i + 1, j] == a) << 4 | int(ul[i + 1, j - 1] == a) << 5
                        | int(ul[i, j - 1] == a) << 6 | int(ul[i - 1, j - 1] == a) << 7)
            else:
                mask = 0
                for r in range(8):
                    y = i - 1 if r in (0, 1, 7) else (i + 1 if r in (3, 4, 5) else i)
                    x = j + 1 if r in (1, 2, 3) else (j - 1 if r in (5, 6, 7) else j)
                    if 0 <= y < hu and 0 <= x < wu and ul[y, x] == a:
                        mask |= 1 << r
            if not _REMOVABLE[mask]:
                continue
            # Move the unit from a to b: perimeters, counts, moments, D', histograms.
            perim[a] += 2.0 * e_a - p_unit
            perim[b] += p_unit - 2.0 * _edges_to(b, nb_lab, nb_w)
            cnt[a] -= u
            cnt[b] += u
            for n in range(nl):
                s1[a, n] -= x1[n]
                s2[a, n] -= x2[n]
                s1[b, n] += x1[n]
                s2[b, n] += x2[n]
            if not energy:  # Eq. 10 of a from its updated moments
                inv = 1.0 / cnt[a]
                for n in range(nl):
                    d_a += _layer_var(inv, s1[a, n], s2[a, n])
            dval[a] = d_a
            dval[b] = d_b
            for v in range(i * s, min(h, (i + 1) * s)):
                for uu in range(j * s, min(w, (j + 1) * s)):
                    for n in range(nl):
                        k = q[v, uu, n]
                        hist[a, n, k] -= 1
                        hist[b, n, k] += 1
            ul[i, j] = b
            moves += 1
    return moves


@numba.njit(cache=True, nogil=True)
def _unit_moments(q: npt.NDArray[np.uint8], centres: npt.NDArray[np.float64], s: int,
                  hu: int, wu: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64],
                                             npt.NDArray[np.float64]]:
    """Per unit of ``s`` x ``s`` cells: cell count and per-layer sums of x and x^2 (Eq. 9).

    The sums run over the unit's cells in raster order, in registers (one layer at a time).
    Whole units of the default block levels (2 and 4) are unrolled: the same additions in the
    same order, without the 2- and 4-trip loops that cost more than the sums (2x faster).
    """
    h, w, nl = q.shape
    uc = np.empty((hu, wu))
    m1 = np.empty((hu, wu, nl))
    m2 = np.empty((hu, wu, nl))
    for i in range(hu):
        v0, v1 = i * s, min(h, (i + 1) * s)
        for j in range(wu):
            u0, u1 = j * s, min(w, (j + 1) * s)
            uc[i, j] = float((v1 - v0) * (u1 - u0))
            whole = v1 - v0 == s and u1 - u0 == s
            for n in range(nl):
                a1, a2 = 0.0, 0.0
                if whole and s == 2:
                    x0 = centres[q[v0, u0, n]]
                    x1 = centres[q[v0, u0 + 1, n]]
                    x2 = centres[q[v0 + 1, u0, n]]
                    x3 = centres[q[v0 + 1, u0 + 1, n]]
                    a1 = a1 + x0 + x1 + x2 + x3
                    a2 = a2 + x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3
                elif whole and s == 4:
                    for v in range(v0, v1):
                        x0 = centres[q[v, u0, n]]
                        x1 = centres[q[v, u0 + 1, n]]
                        x2 = centres[q[v, u0 + 2, n]]
                        x3 = centres[q[v, u0 + 3, n]]
                        a1 = a1 + x0 + x1 + x2 + x3
                        a2 = a2 + x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3
                else:
                    for v in range(v0, v1):
                        for u in range(u0, u1):
                            x = centres[q[v, u, n]]
                            a1 += x
                            a2 += x * x
                m1[i, j, n] = a1
                m2[i, j, n] = a2
    return uc, m1, m2


@numba.njit(cache=True, nogil=True)
def run(qt: npt.NDArray[np.uint8], labels: npt.NDArray[np.int32],
         sizes: npt.NDArray[np.int64], sweeps: npt.NDArray[np.int64],
         cnt: npt.NDArray[np.float64], s1: npt.NDArray[np.float64],
         s2: npt.NDArray[np.float64], perim: npt.NDArray[np.float64],
         dval: npt.NDArray[np.float64], hist: npt.NDArray[np.int32],
         centres: npt.NDArray[np.float64], gamma: float, energy: bool, block: int,
         margin: int, door: npt.NDArray[np.uint8],
         w_door: float) -> tuple[npt.NDArray[np.int32], int]:
    """The whole schedule: ``sweeps[l]`` alternating sweeps of units of ``sizes[l]`` cells.

    Returns the cell labels and the number of moves; ``block`` and ``margin`` bound every
    supercell's extent and ``door`` / ``w_door`` reward doorway lines (:func:`_sweep`).
    ``labels`` is updated in place when the schedule is only cell level.  One call from
    Python, not one per sweep with the per-level setup (unit grid, edge lengths, label
    expansion) in numpy around them.
    """
    h, w = labels.shape
    cols = -(-w // block)
    moves = 0
    for lev in range(sizes.size):
        s = sizes[lev]
        hu, wu = -(-h // s), -(-w // s)
        if s == 1:
            ul = labels
            uc, m1, m2 = np.ones((1, 1)), np.zeros((1, 1, 1)), np.zeros((1, 1, 1))
        else:
            ul = np.empty((hu, wu), np.int32)  # blocks nest: each is one label
            for i in range(hu):
                for j in range(wu):
                    ul[i, j] = labels[i * s, j * s]
            uc, m1, m2 = _unit_moments(qt, centres, s, hu, wu)
        rh = np.empty(hu)
        for i in range(hu):
            rh[i] = min(s, h - s * i)
        cw = np.empty(wu)
        for j in range(wu):
            cw[j] = min(s, w - s * j)
        for sweep in range(sweeps[lev]):
            moves += _sweep(ul, uc, m1, m2, rh, cw, qt, s, cnt, s1, s2, perim, dval, hist,
                            centres, gamma, energy, sweep % 2 == 1, cols, block, margin, door,
                            w_door)
        if s > 1:
            labels = np.empty((h, w), np.int32)
            for v in range(h):
                for u in range(w):
                    labels[v, u] = ul[v // s, u // s]
    return labels, moves



@numba.njit(cache=True, nogil=True)
def quantize_hwn(p: npt.NDArray[np.float32], bins: int) -> npt.NDArray[np.uint8]:
    """``(N, H, W)`` probabilities -> ``(H, W, N)`` bin indices (cell-major for the sweeps)."""
    nl, h, w = p.shape
    out = np.empty((h, w, nl), np.uint8)
    for n in range(nl):  # reads contiguous, writes strided: faster than the other way round
        for v in range(h):
            for u in range(w):
                k = int(p[n, v, u] * bins)
                out[v, u, n] = min(max(k, 0), bins - 1)
    return out


@numba.njit(cache=True, nogil=True)
def supercell_state(
    qt: npt.NDArray[np.uint8], labels: npt.NDArray[np.int32], count: int,
    centres: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64],
           npt.NDArray[np.int32], npt.NDArray[np.float64]]:
    """Count, moments (sums of x, x^2), per-layer histograms ``(S, N, K)`` and perimeters
    (4-neighbour edges to another label) per supercell."""
    h, w, nl = qt.shape
    hist = np.zeros((count, nl, centres.size), np.int32)
    cnt = np.zeros(count)
    perim = np.zeros(count)
    for v in range(h):
        for u in range(w):
            c = labels[v, u]
            cnt[c] += 1.0
            for n in range(nl):
                hist[c, n, qt[v, u, n]] += 1
            if u + 1 < w and labels[v, u + 1] != c:
                perim[c] += 1.0
                perim[labels[v, u + 1]] += 1.0
            if v + 1 < h and labels[v + 1, u] != c:
                perim[c] += 1.0
                perim[labels[v + 1, u]] += 1.0
    s1 = np.zeros((count, nl))
    s2 = np.zeros((count, nl))
    for c in range(count):
        for n in range(nl):
            for k in range(centres.size):
                s1[c, n] += hist[c, n, k] * centres[k]
                s2[c, n] += hist[c, n, k] * centres[k] * centres[k]
    return cnt, s1, s2, hist, perim

