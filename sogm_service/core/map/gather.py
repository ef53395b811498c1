"""Sparse sampling of coarse windows: read only the map cells each output cell needs.

:meth:`~sogm_service.core.map.tiles.TiledMap.sample` builds the window's whole box at map
resolution (the *mosaic*) and warps it with OpenCV.  For a window much coarser than the map
that reads far more cells than it returns (a 100 x 100 reply of a 400 m window at 4 m cells
on a 5 cm map reads 8002 x 8002 cells per layer).  The *gather* path instead works out, for
every output cell centre, the source cells the warp would read (its *taps*: 1 for nearest,
the 2 x 2 neighbours for bilinear and biodds), fetches only those from the tiles and
interpolates them.  The cost is proportional to the reply, not to the window's area.

Agreement with the mosaic path.  The taps are computed from the same 2 x 3 matrix the warp
gets (``dst_to_src`` of the same box) with the same arithmetic OpenCV 5 uses:

* ``nearest`` (int16 images) and ``bilinear`` (float64 probabilities): OpenCV's classic
  fixed-point remap, positions in 1/1024 cell rounded with ``cvRound`` (half to even), the
  bilinear fraction quantised to 1/32 cell.  Integer arithmetic: the same on every CPU, so
  nearest is bit-identical and bilinear equal to within one fixed-point step.
* ``biodds`` (float32 log-odds): OpenCV 5's SIMD kernel computes positions in float32 with a
  fused multiply-add per vector of ``uf`` lanes and a scalar tail.  Which one it runs depends
  on the CPU, so :func:`float32_mode` finds it once with a tiny probe warp; when no known
  mode matches, positions are exact (float64) and may differ from the warp's by one float32
  rounding (below 5e-4 cell in an 8000-cell box).

Everything here is pure (numpy, and cv2 only for the probe); the tile reads live in
:meth:`~sogm_service.core.map.tiles.TiledMap.gather`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.map.footprint import gather_taps
from sogm_service.core.resample import Interp

_AB_BITS = 10  # OpenCV's fixed-point position bits (AB_SCALE = 1024)
_INTER_BITS = 5  # OpenCV's bilinear fraction bits (INTER_TAB_SIZE = 32)


@dataclass(frozen=True, slots=True)
class Taps:
    """The source cells of every output cell: ``u``, ``v`` (``(K, H, W)`` int64, cells of
    the mosaic box), ``inside`` (whether each lies in that box; the warp reads 0 outside it)
    and the bilinear ``fu``, ``fv`` fractions (``(H, W)``; None for nearest)."""

    u: npt.NDArray[np.int64]
    v: npt.NDArray[np.int64]
    inside: npt.NDArray[np.bool_]
    fu: npt.NDArray[np.float64] | None
    fv: npt.NDArray[np.float64] | None


def taps(m: npt.NDArray[np.float64], box_w: int, box_h: int, width: int, height: int,
         interp: Interp) -> Taps:
    """The cells of a ``box_w x box_h`` box that warping it with the 2 x 3 inverse map ``m``
    into ``width x height`` cells reads, as :func:`sogm_service.core.resample.resample_stack`
    does it for ``interp``."""
    if interp == "nearest":
        iu, iv = _fixed_positions(m, width, height, _AB_BITS, 1 << (_AB_BITS - 1))
        u, v = iu[None], iv[None]
        fu = fv = None
    else:
        if interp == "bilinear":
            xu, xv = _fixed_positions(m, width, height, _AB_BITS - _INTER_BITS,
                                      1 << (_AB_BITS - _INTER_BITS - 1))
            iu, iv = xu >> _INTER_BITS, xv >> _INTER_BITS
            scale = float(1 << _INTER_BITS)
            fu = (xu & ((1 << _INTER_BITS) - 1)) / scale
            fv = (xv & ((1 << _INTER_BITS) - 1)) / scale
        else:
            su, sv = _float32_positions(m, width, height)
            iu, iv = np.floor(su).astype(np.int64), np.floor(sv).astype(np.int64)
            fu, fv = su - iu, sv - iv
        u = np.stack([iu, iu + 1, iu, iu + 1])
        v = np.stack([iv, iv, iv + 1, iv + 1])
    inside = (u >= 0) & (u < box_w) & (v >= 0) & (v < box_h)
    return Taps(u, v, inside, fu, fv)


def combine(values: npt.NDArray[np.int16], t: Taps, interp: Interp) -> npt.NDArray[np.int16]:
    """``(L, H, W)`` log-odds from the ``(L, K, H, W)`` tap values (0 where not ``inside``),
    interpolated as the warp does for ``interp``."""
    if interp == "nearest":
        return np.ascontiguousarray(values[:, 0])
    assert t.fu is not None and t.fv is not None
    g: npt.NDArray[np.floating] = values.astype(np.float64)
    if interp == "bilinear":  # on probabilities; outside the box the warp reads P = 0.5
        g = logodds.sigmoid(g / logodds.SCALE)
    fu, fv = t.fu, t.fv
    top = g[:, 0] + fu * (g[:, 1] - g[:, 0])
    bottom = g[:, 2] + fu * (g[:, 3] - g[:, 2])
    out = top + fv * (bottom - top)
    if interp == "biodds":
        # The warp's float32 result, rounded as resample_stack rounds it.
        return np.rint(out.astype(np.float32)).astype(np.int16)
    return logodds.to_fixed(logodds.logit(np.clip(out, 1e-12, 1 - 1e-12)))


def tap_count(width: int, height: int, interp: Interp) -> int:
    """How many cells (per layer) the gather reads for a ``width x height`` reply."""
    return gather_taps(interp) * width * height


# -- positions as OpenCV computes them ------------------------------------------------------
def _fixed_positions(m: npt.NDArray[np.float64], width: int, height: int, shift: int,
                     delta: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """OpenCV's classic warpAffine: ``adelta = cvRound(M0 x 1024)``, ``X0 = cvRound((M1 y +
    M2) 1024) + delta``, position ``(X0 + adelta) >> shift`` (``cvRound``: half to even, as
    ``np.rint``)."""
    scale = float(1 << _AB_BITS)
    xs = np.arange(width, dtype=np.float64)
    ys = np.arange(height, dtype=np.float64)
    out = []
    for r in (0, 1):
        adelta = np.rint(m[r, 0] * xs * scale).astype(np.int64)
        x0 = np.rint((m[r, 1] * ys + m[r, 2]) * scale).astype(np.int64) + delta
        out.append((x0[:, None] + adelta[None, :]) >> shift)
    return out[0], out[1]


def _fma32(a: npt.ArrayLike, b: npt.ArrayLike, c: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """float32 fused multiply-add: the float32 product is exact in float64 (48 bits)."""
    return (np.asarray(a, np.float64) * np.asarray(b, np.float64)
            + np.asarray(c, np.float64)).astype(np.float32)


@dataclass(frozen=True, slots=True)
class Float32Mode:
    """How OpenCV 5's float32 linear warp computes positions on this CPU: vectors of
    ``lanes`` columns (while ``x <= width - lanes``) as ``fma(M0, x, Mx)`` (``fused``) or a
    float32 product and sum, with ``Mx = float32(y M1 + M2)``; the other columns as
    ``fma(x, M0, y M1) + M2``."""

    lanes: int
    fused: bool


def _f32_positions(mode: Float32Mode | None, m: npt.NDArray[np.float64], width: int,
                   height: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    if mode is None:  # exact positions
        x64 = np.arange(width, dtype=np.float64)[None, :]
        y64 = np.arange(height, dtype=np.float64)[:, None]
        return (m[0, 0] * x64 + m[0, 1] * y64 + m[0, 2], m[1, 0] * x64 + m[1, 1] * y64 + m[1, 2])
    m32 = m.astype(np.float32)
    xs = np.arange(width, dtype=np.float32)
    ys = np.arange(height, dtype=np.float32)[:, None]
    nvec = 0 if width < mode.lanes else (width // mode.lanes) * mode.lanes
    out = []
    for r in (0, 1):
        a, b, c = m32[r, 0], m32[r, 1], m32[r, 2]
        row = ys * b + c  # float32: OpenCV's Mx
        pos = np.empty((height, width), dtype=np.float32)
        xv = xs[None, :nvec]
        pos[:, :nvec] = _fma32(a, xv, row) if mode.fused else a * xv + row
        xt = xs[None, nvec:]
        pos[:, nvec:] = _fma32(xt, a, ys * b) + c
        out.append(pos.astype(np.float64))
    return out[0], out[1]


def _float32_positions(m: npt.NDArray[np.float64], width: int,
                       height: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    return _f32_positions(float32_mode(), m, width, height)


_PROBES = (np.array([[37.3719, 0.0137, 5123.77], [0.0, 0.0, 0.25]]),
           np.array([[-11.000173, -0.731, 7711.1], [0.0, 0.0, 0.5]]),
           np.array([[40.0, 0.05, 4000.5], [0.0, 0.0, 0.75]]))


@functools.cache
def float32_mode() -> Float32Mode | None:
    """The :class:`Float32Mode` that reproduces OpenCV's float32 warp positions exactly on
    this machine (found once with a probe warp of a 2 x 8192 image), or None."""
    width_src = 8192
    odd = (np.arange(width_src) % 2).astype(np.float32)
    img = np.ascontiguousarray(np.broadcast_to(odd, (2, width_src)))
    w, h = 71, 5
    seen = []
    for m in _PROBES:
        got = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        seen.append(got.astype(np.float64))
    for lanes in (16, 8, 32, 4, 64):
        for fused in (True, False):
            mode = Float32Mode(lanes, fused)
            if all(_probe_matches(mode, m, got, w, h) for m, got in zip(_PROBES, seen,
                                                                        strict=True)):
                return mode
    return None


def _probe_matches(mode: Float32Mode, m: npt.NDArray[np.float64],
                   got: npt.NDArray[np.float64], w: int, h: int) -> bool:
    su, _ = _f32_positions(mode, m, w, h)
    iu = np.floor(su)
    frac = su - iu
    # On the 0/1 pattern the warp returns frac at even cells and 1 - frac at odd ones.
    want = np.where(iu.astype(np.int64) % 2 == 0, frac, 1.0 - frac)
    return bool(np.array_equal(want, got))
