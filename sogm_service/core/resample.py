"""Resampling grids between geometries: nearest, bilinear and the paper's biodds (Eq. 3-5).

Every function maps a grid given in one :class:`~sogm_service.core.geometry.GridGeometry` onto
another (any relative yaw, scale and offset).  Destination cells whose source position lies
outside the source grid are *unknown* (P = 0.5, log-odds 0), never zero.

Biodds (paper Eq. 3-5) interpolates the amount of evidence rather than the probability.  With
``f(x) = 0.5 tanh((x - 0.5) a) + 0.5`` and ``a = 2 atanh(1 - 2 eps0)``, Eq. 5 equals
``sigmoid(bilinear(logit(clip(p, eps0, 1 - eps0))))`` exactly (DESIGN.md section 1: ``a``
cancels; ``eps0`` moves it between nearest-like, eps0 -> 0, and bilinear-like, eps0 -> 0.5).
So biodds is *bilinear interpolation of clamped log-odds*, which is what the map stores: the
fast path is one OpenCV warp of the log-odds grid.

OpenCV's integer warps quantise the sub-cell position to 1/32 cell (``INTER_BITS = 5``); its
float32 warp (measured with OpenCV 5.0) interpolates at the exact position, so biodds warps
float32 log-odds and rounds.  The tests check it against an exact numpy oracle
(``tests/oracles.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice, wrap_angle

Interp = Literal["biodds", "bilinear", "nearest"]
INTERPOLATIONS: tuple[Interp, ...] = ("biodds", "bilinear", "nearest")

_CV_FLAGS = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR}


def dst_to_src(src: GridGeometry, dst: GridGeometry) -> npt.NDArray[np.float64]:
    """3x3 affine taking destination cell coordinates to source cell coordinates."""
    return src.world_to_cell() @ dst.cell_to_world()


def warp(
    grid: npt.NDArray,
    src: GridGeometry,
    dst: GridGeometry,
    interp: Literal["nearest", "linear"],
    border_value: float,
) -> npt.NDArray:
    """Sample a 2-D ``grid`` (shape ``src.shape``) at every cell centre of ``dst``.

    ``interp`` is ``nearest`` or ``linear`` (bilinear in the grid's own values); positions
    outside the source get ``border_value``.  The dtype is kept (float32, int16, uint8).
    """
    if grid.shape != src.shape:
        raise ValueError(f"grid shape {grid.shape} does not match geometry {src.shape}")
    if dst.width == 0 or dst.height == 0:
        return np.zeros(dst.shape, dtype=grid.dtype)
    if src.width == 0 or src.height == 0:
        return np.full(dst.shape, border_value, dtype=grid.dtype)
    m = dst_to_src(src, dst)[:2]
    return cv2.warpAffine(
        grid, m, (dst.width, dst.height),
        flags=_CV_FLAGS[interp] | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT, borderValue=border_value,
    )


def resample_logodds(
    l: npt.NDArray[np.int16],
    src: GridGeometry,
    dst: GridGeometry,
    interp: Interp = "biodds",
) -> npt.NDArray[np.int16]:
    """Resample a fixed-point log-odds grid (``int16``) into ``dst``; outside -> 0 (unknown).

    * ``biodds``: bilinear on the (already clamped) log-odds - Eq. 5.
    * ``bilinear``: bilinear on probabilities, converted back to log-odds.
    * ``nearest``: nearest cell.
    """
    if interp == "biodds":
        # In float32: OpenCV's float warp interpolates at the exact position (its int16 warp
        # rounds the position to 1/32 cell) and is ~4x faster; rint = OpenCV's own rounding.
        out = warp(l.astype(np.float32), src, dst, "linear", 0.0)
        return np.rint(out).astype(np.int16)
    if interp == "nearest":
        return warp(l, src, dst, "nearest", 0.0)
    if interp == "bilinear":
        # float64: in float32, P within 1e-7 of 1 (the widest clamp, 16 nats) keeps only a few
        # bits, and the way back to log-odds was off by up to ~0.1 nat even for an identity.
        p = logodds.sigmoid(np.asarray(l, dtype=np.float64) / logodds.SCALE)
        q = warp(p, src, dst, "linear", 0.5)
        return logodds.to_fixed(logodds.logit(np.clip(q, 1e-12, 1 - 1e-12)))
    raise ValueError(f"unknown interpolation {interp!r}; use one of {INTERPOLATIONS}")


def resample_stack(
    stack: npt.NDArray[np.int16],
    src: GridGeometry,
    dst: GridGeometry,
    interp: Interp = "biodds",
) -> npt.NDArray[np.int16]:
    """:func:`resample_logodds` for every layer of an ``(N, H, W)`` stack."""
    if interp == "biodds" and stack.size and dst.width and dst.height:
        return _biodds_stack(stack, src, dst)
    out = np.zeros((stack.shape[0], *dst.shape), dtype=np.int16)
    for n in range(stack.shape[0]):
        out[n] = resample_logodds(stack[n], src, dst, interp)
    return out


def _biodds_stack(stack: npt.NDArray[np.int16], src: GridGeometry,
                  dst: GridGeometry) -> npt.NDArray[np.int16]:
    """Biodds of every layer as :func:`resample_logodds` does it, with the transform, the
    float conversion and the rounding done once for the whole stack (the submap hot path)."""
    if stack.shape[1:] != src.shape:
        raise ValueError(f"stack shape {stack.shape} does not match geometry {src.shape}")
    m = dst_to_src(src, dst)[:2]
    grids = stack.astype(np.float32)
    out = np.empty((stack.shape[0], *dst.shape), dtype=np.float32)
    for n in range(stack.shape[0]):
        cv2.warpAffine(grids[n], m, (dst.width, dst.height), dst=out[n],
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return np.rint(out, out=out).astype(np.int16)


# -- fusing into a tile lattice (the hot path of TiledMap.fuse) -------------------------------
ALIGN_TOL = 1e-6
"""Cells: how far from the lattice a grid may sit and still count as aligned."""


@dataclass(frozen=True, slots=True)
class TilePatch:
    """The part of an ISM that lands in one tile: cell block ``(u0, v0, w, h)`` and ``patch``.

    ``patch`` is int16 fixed log-odds, or float32 for biodds (OpenCV's float warp is ~4x faster
    than its int16 one; :func:`sogm_service.core.logodds.bayes_update` rounds while adding).
    """

    index: tuple[int, int]
    block: tuple[int, int, int, int]
    patch: npt.NDArray


Buffers = Callable[[int, int, np.dtype], npt.NDArray]
"""Memory for one warped block: ``(h, w, dtype) -> (h, w)`` array (:func:`tile_patches`)."""


def lattice_offset(src: GridGeometry, resolution: float) -> tuple[int, int] | None:
    """Map cell ``(column, row)`` of ``src``'s cell (0, 0) when ``src`` sits on the lattice's
    cells (same resolution and heading, origin on a cell corner), else None."""
    if abs(src.resolution - resolution) > ALIGN_TOL * resolution:
        return None
    yaw = wrap_angle(src.origin.yaw)
    if abs(yaw) > 1e-9:
        return None
    u, v = src.origin.x / resolution, src.origin.y / resolution
    cu, cv = round(u), round(v)
    if abs(u - cu) >= ALIGN_TOL or abs(v - cv) >= ALIGN_TOL:
        return None
    return cu, cv


def tile_block(corners: npt.NDArray[np.float64], index: tuple[int, int],
               tile_size: int) -> tuple[int, int, int, int] | None:
    """Cell block ``(u0, v0, w, h)`` of tile ``index`` that a grid with ``corners`` (in map
    cells, ``(4, 2)``) may cover, or None."""
    t = tile_size
    u = corners[:, 0] - index[0] * t
    v = corners[:, 1] - index[1] * t
    u0 = max(0, math.floor(u.min() + ALIGN_TOL))
    v0 = max(0, math.floor(v.min() + ALIGN_TOL))
    u1 = min(t, math.ceil(u.max() - ALIGN_TOL))
    v1 = min(t, math.ceil(v.max() - ALIGN_TOL))
    if u1 <= u0 or v1 <= v0:
        return None
    return u0, v0, u1 - u0, v1 - v0


def tile_patches(inc: npt.NDArray[np.int16], geometry: GridGeometry, lattice: TileLattice,
                 interp: Interp = "biodds",
                 owned: Callable[[tuple[int, int]], bool] | None = None,
                 buffers: Buffers | None = None) -> Iterator[TilePatch]:
    """Every tile's share of the increments ``inc`` (given in ``geometry``), raster order;
    with ``owned``, only the tiles it accepts (a fuse worker's share of the lattice).

    Aligned ISMs are sliced (views, no copy); others are warped block by block, the ISM's
    inverse transform computed once, into one scratch buffer: a warped patch is valid only
    until the next one is produced (consume it at once) -- unless ``buffers`` gives each
    block's memory (``(h, w, dtype) -> array``), as :meth:`TiledMap.fuse` does to keep every
    patch of an ISM until it has added them all.
    """
    if interp not in INTERPOLATIONS:
        raise ValueError(f"unknown interpolation {interp!r}; use one of {INTERPOLATIONS}")
    if inc.size == 0:
        return
    offset = lattice_offset(geometry, lattice.resolution)
    if offset is not None:
        for part in _aligned_patches(inc, offset, lattice.tile_size):
            if owned is None or owned(part.index):
                yield part
        return
    res, t = lattice.resolution, lattice.tile_size
    corners = geometry.corners() / res
    to_src = geometry.world_to_cell()
    # float32: OpenCV's bilinear warp of float is ~4x faster than of int16 (SIMD).
    src = inc.astype(np.float32) if interp == "biodds" else inc
    # One tile-sized buffer for every block: fresh arrays of this size are mmapped and
    # page-faulted on every call by glibc, which costs as much as the warp itself.
    scratch = np.empty((t, t), dtype=src.dtype) if buffers is None else None
    for index in lattice.tiles_overlapping(geometry):
        if owned is not None and not owned(index):
            continue
        block = tile_block(corners, index, t)
        if block is None:
            continue
        u0, v0, w, h = block
        x0, y0 = index[0] * lattice.span + u0 * res, index[1] * lattice.span + v0 * res
        if interp == "bilinear":  # on probabilities: the rare, slow path
            sub = GridGeometry(res, w, h, Pose2D(x0, y0, 0.0))
            yield TilePatch(index, block, resample_logodds(inc, geometry, sub, interp))
            continue
        c2w = np.array([[res, 0.0, x0 + 0.5 * res], [0.0, res, y0 + 0.5 * res], [0, 0, 1.0]])
        if buffers is not None:
            out = buffers(h, w, src.dtype)
        else:
            assert scratch is not None
            out = scratch[:h, :w]
        yield TilePatch(index, block, _warp_block(src, to_src @ c2w, out, interp))


def _aligned_patches(inc: npt.NDArray[np.int16], offset: tuple[int, int],
                     t: int) -> Iterator[TilePatch]:
    cu, cv = offset
    h, w = inc.shape
    for j in range(cv // t, (cv + h - 1) // t + 1):
        v0, v1 = max(cv, j * t), min(cv + h, (j + 1) * t)
        for i in range(cu // t, (cu + w - 1) // t + 1):
            u0, u1 = max(cu, i * t), min(cu + w, (i + 1) * t)
            yield TilePatch((i, j), (u0 - i * t, v0 - j * t, u1 - u0, v1 - v0),
                            inc[v0 - cv:v1 - cv, u0 - cu:u1 - cu])


def _warp_block(src: npt.NDArray, m: npt.NDArray[np.float64], out: npt.NDArray,
                interp: Interp) -> npt.NDArray:
    """``src`` sampled into ``out``, the cells of an axis-aligned block; ``m``: block cells ->
    src cells."""
    flag = cv2.INTER_LINEAR if interp == "biodds" else cv2.INTER_NEAREST
    h, w = out.shape
    done: npt.NDArray = cv2.warpAffine(src, m[:2], (w, h), dst=out,
                                       flags=flag | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return done


def informative(patch: npt.NDArray) -> bool:
    """Whether adding ``patch`` changes anything (float patches round half to even)."""
    if patch.dtype == np.float32:
        return bool((np.abs(patch) > 0.5).any())
    return bool(patch.any())
