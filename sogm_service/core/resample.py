"""Resampling grids between geometries: nearest, bilinear and the paper's biodds (Eq. 3-5).

Every function maps a grid given in one :class:`~sogm_service.core.geometry.GridGeometry` onto
another (any relative yaw, scale and offset).  Destination cells whose source position lies
outside the source grid are *unknown* (P = 0.5, log-odds 0), never zero.

Biodds (paper Eq. 3-5) interpolates the amount of evidence rather than the probability.  With
``f(x) = 0.5 tanh((x - 0.5) a) + 0.5`` and ``a = 2 atanh(1 - 2 eps0)``, Eq. 5 equals
``sigmoid(bilinear(logit(clip(p, eps0, 1 - eps0))))`` exactly (architecture, section 1,
docs/architecture.md#1-log-odds-everywhere: ``a``
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
import threading
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

    ``patch`` is int16 fixed log-odds (biodds warps float32 and rounds once per band).
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


def tile_block(box: tuple[int, int, int, int], index: tuple[int, int],
               tile_size: int) -> tuple[int, int, int, int] | None:
    """Cell block ``(u0, v0, w, h)`` of tile ``index`` that a grid with footprint ``box``
    (:func:`footprint_box`) may cover, or None."""
    t = tile_size
    u0, v0 = max(0, box[0] - index[0] * t), max(0, box[1] - index[1] * t)
    u1, v1 = min(t, box[2] - index[0] * t), min(t, box[3] - index[1] * t)
    if u1 <= u0 or v1 <= v0:
        return None
    return u0, v0, u1 - u0, v1 - v0


def tile_patches(inc: npt.NDArray[np.int16], geometry: GridGeometry, lattice: TileLattice,
                 interp: Interp = "biodds",
                 owned: Callable[[tuple[int, int]], bool] | None = None,
                 buffers: Buffers | None = None) -> Iterator[TilePatch]:
    """Every tile's share of the increments ``inc`` (given in ``geometry``), raster order;
    with ``owned``, only the tiles it accepts (a fuse worker's share of the lattice).

    Aligned ISMs are sliced (views, no copy).  Others are warped one band a row of tiles at a
    time: the footprint's full width times the row's part of it, the ISM's inverse transform
    computed once, each tile's patch a view of its band.  A band, not a tile: every OpenCV call
    costs ~15 us beyond its cells (its thread pool's hand-off), 25 tiles' worth of which was
    as much as half the warp of a 512x512 ISM.  Bands span the whole footprint whatever
    ``owned`` says, so a cell's value never depends on who fuses it (OpenCV's float warp
    differs in the last bits with the block's origin): any number of fuse workers, and any
    cluster member, writes the same bits.  Biodds bands are rounded to int16 once (half to
    even, as the add would).  A patch is valid until this thread produces the next band
    (consume it at once) -- unless ``buffers`` gives each band's int16 memory (``(h, w,
    dtype) -> array``), as :meth:`TiledMap.fuse` does to keep every patch of an ISM until it
    has added them all (2 bytes a footprint cell; the float32 warp is passing memory).
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
    box = footprint_box(geometry.corners() / lattice.resolution)
    bands = _Bands(inc, geometry, lattice, interp, box, buffers)
    for index in lattice.tiles_overlapping(geometry):
        if owned is not None and not owned(index):
            continue
        block = tile_block(box, index, lattice.tile_size)
        if block is None:
            continue
        if interp == "bilinear":  # on probabilities: the rare, slow path
            yield TilePatch(index, block, _bilinear_block(inc, geometry, lattice, index, block))
            continue
        yield TilePatch(index, block, bands.patch(index, block))


def footprint_box(corners: npt.NDArray[np.float64]) -> tuple[int, int, int, int]:
    """Map cells ``(u0, v0, u1, v1)`` (end exclusive) that a grid with ``corners`` (in map
    cells) may cover; within a tile, :func:`tile_block`."""
    return (math.floor(corners[:, 0].min() + ALIGN_TOL),
            math.floor(corners[:, 1].min() + ALIGN_TOL),
            math.ceil(corners[:, 0].max() - ALIGN_TOL),
            math.ceil(corners[:, 1].max() - ALIGN_TOL))


class _Bands:
    """The warped bands of one ISM (:func:`tile_patches`), made on first use."""

    def __init__(self, inc: npt.NDArray[np.int16], geometry: GridGeometry, lattice: TileLattice,
                 interp: Interp, box: tuple[int, int, int, int],
                 buffers: Buffers | None) -> None:
        # float32: OpenCV's bilinear warp of float is ~4x faster than of int16 (SIMD).
        self.src = inc.astype(np.float32) if interp == "biodds" else inc
        self.to_src = geometry.world_to_cell()
        self.lattice, self.interp, self.buffers = lattice, interp, buffers
        self.box = box
        self.row: int | None = None  # the tile row of ``band``
        self.band: npt.NDArray[np.int16] = np.empty((0, 0), np.int16)
        self.v0 = 0

    def patch(self, index: tuple[int, int], block: tuple[int, int, int, int]) -> npt.NDArray:
        if index[1] != self.row:
            self._warp_row(index[1])
        t, (u0, v0, w, h) = self.lattice.tile_size, block
        gu, gv = index[0] * t + u0 - self.box[0], index[1] * t + v0 - self.v0
        return self.band[gv:gv + h, gu:gu + w]

    def _warp_row(self, j: int) -> None:
        t, res = self.lattice.tile_size, self.lattice.resolution
        u0, vmin, u1, vmax = self.box
        v0, v1 = max(vmin, j * t), min(vmax, (j + 1) * t)
        h, w = v1 - v0, u1 - u0
        c2w = np.array([[res, 0.0, (u0 + 0.5) * res], [0.0, res, (v0 + 0.5) * res], [0, 0, 1.0]])
        m = self.to_src @ c2w
        if self.interp == "nearest":  # int16 in, int16 out
            band = _warp_block(self.src, m, self._kept(h, w), self.interp)
        else:  # biodds: warped in float32 (passing), rounded once into the band that is kept
            warped = _warp_block(self.src, m, _passing_float(h, w), self.interp)
            band = np.rint(warped, out=self._kept(h, w), casting="unsafe")
        self.row, self.band, self.v0 = j, band, v0

    def _kept(self, h: int, w: int) -> npt.NDArray[np.int16]:
        """The band's int16 memory: from ``buffers`` (kept until the fuse has added every
        patch), else this thread's one reused band (valid until the next)."""
        if self.buffers is not None:
            return self.buffers(h, w, np.dtype(np.int16))
        return _reused(h, w, np.dtype(np.int16), "kept")


_band_memory = threading.local()

_REUSED_MAX = 16 << 20
"""Bytes: bands beyond this get fresh memory instead of growing the thread's reused one."""


def _passing_float(h: int, w: int) -> npt.NDArray[np.float32]:
    return _reused(h, w, np.dtype(np.float32), "float")


def _reused(h: int, w: int, dtype: np.dtype, role: str) -> npt.NDArray:
    """This thread's reused ``(h, w)`` array for ``role`` (fresh arrays of a band's size are
    mmapped and page-faulted by glibc on every call, which costs as much as the warp)."""
    if h * w * dtype.itemsize > _REUSED_MAX:
        return np.empty((h, w), dtype)
    buf: npt.NDArray | None = getattr(_band_memory, role, None)
    if buf is None or buf.size < h * w:
        grown = min(2 * (0 if buf is None else buf.size), _REUSED_MAX // dtype.itemsize)
        buf = np.empty(max(h * w, grown), dtype)
        setattr(_band_memory, role, buf)
    return buf[:h * w].reshape(h, w)


def _bilinear_block(inc: npt.NDArray[np.int16], geometry: GridGeometry, lattice: TileLattice,
                    index: tuple[int, int], block: tuple[int, int, int, int]
                    ) -> npt.NDArray[np.int16]:
    res, (u0, v0, w, h) = lattice.resolution, block
    x0, y0 = index[0] * lattice.span + u0 * res, index[1] * lattice.span + v0 * res
    return resample_logodds(inc, geometry, GridGeometry(res, w, h, Pose2D(x0, y0, 0.0)),
                            "bilinear")


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


def informative(patch: npt.NDArray[np.int16]) -> bool:
    """Whether adding ``patch`` changes anything."""
    return bool(patch.any())
