"""Slow, exact references the fast paths are checked against (test oracles, not product code)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.resample import INTERPOLATIONS, Interp, warp


def resample_prob(
    p: npt.NDArray,
    src: GridGeometry,
    dst: GridGeometry,
    interp: Interp = "biodds",
    eps0: float = logodds.DEFAULT_EPS0,
) -> npt.NDArray[np.float32]:
    """Resample a probability grid into ``dst``; outside the source -> 0.5 (unknown).

    ``eps0`` is the clamp of biodds (paper Eq. 3); it is ignored by the other two.
    """
    p32 = np.asarray(p, dtype=np.float32)
    if interp == "nearest":
        return warp(p32, src, dst, "nearest", 0.5)
    if interp == "bilinear":
        return warp(p32, src, dst, "linear", 0.5)
    if interp == "biodds":
        eps0 = logodds.check_eps0(eps0)  # eps0 = 0 gave logit +-inf and NaN cells
        # Clamp in float64: float32(1 - eps0) is not 1 - eps0 (for eps0 = 1e-6 the upper bound
        # became 13.80 nats against a lower bound of -13.82), which skewed Eq. 3's bounds.
        clamped = np.clip(np.asarray(p, dtype=np.float64), eps0, 1.0 - eps0)
        l = logodds.logit(clamped).astype(np.float32)
        out = warp(l, src, dst, "linear", 0.0)
        return logodds.sigmoid(out).astype(np.float32)
    raise ValueError(f"unknown interpolation {interp!r}; use one of {INTERPOLATIONS}")


def sample_bilinear(
    grid: npt.NDArray, u: npt.NDArray, v: npt.NDArray, border_value: float
) -> npt.NDArray[np.float64]:
    """Exact bilinear interpolation of ``grid`` at continuous cell coordinates ``(u, v)``.

    Cell centres sit on integers; a neighbour outside the grid contributes ``border_value``
    (as OpenCV's constant border does).  The slow, exact counterpart of
    :func:`sogm_service.core.resample.warp`.
    """
    g = np.asarray(grid, dtype=np.float64)
    padded = np.pad(g, 1, constant_values=border_value)
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u0 = np.floor(u)
    v0 = np.floor(v)
    fu = u - u0
    fv = v - v0
    # +1 for the padding; indices beyond the pad read the border value as well.
    iu = np.clip(u0.astype(np.int64) + 1, 0, padded.shape[1] - 2)
    iv = np.clip(v0.astype(np.int64) + 1, 0, padded.shape[0] - 2)
    outside = (u0 < -1) | (v0 < -1) | (u0 > g.shape[1] - 1) | (v0 > g.shape[0] - 1)
    top = padded[iv, iu] * (1 - fu) + padded[iv, iu + 1] * fu
    bottom = padded[iv + 1, iu] * (1 - fu) + padded[iv + 1, iu + 1] * fu
    out = top * (1 - fv) + bottom * fv
    return np.where(outside, border_value, out)
