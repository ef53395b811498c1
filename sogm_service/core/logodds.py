"""Fixed-point log-odds: the one representation behind every map operation.

A cell of semantic layer *n* stores ``l = logit(P(m_n | z_1:t))`` (architecture, section 1:
docs/architecture.md#1-log-odds-everywhere) as an
``int16`` in units of ``1 / SCALE`` nat (``SCALE = 1000``: one unit is a thousandth of a nat).

Why int16: the map is memory-bound (one add and one clamp per cell per ISM); int16 halves the
traffic of float32.  Overflow is impossible by construction: the map state is clamped to
``|l| <= MAX_STATE`` and every increment to ``|inc| <= MAX_STATE``, so ``state + inc`` stays
within ``2 * MAX_STATE = 32000 < 32767`` before the clamp brings it back.

Paper equations implemented here:

* Eq. 1, the recursive Bayesian update, is a product of odds, i.e. a sum of log-odds:
  ``l_t = clamp(l_{t-1} + logit(P(m | z_t, x_t)))`` (:func:`bayes_update`).
* Eq. 6, super-Bayesian independent opinion pool ``P_B``: a sum of log-odds over layers
  (:func:`fuse_bayes`); max pooling ``P_M``: a max over the layers that observed the cell,
  because logit is monotone and a layer without evidence there has no opinion
  (:func:`fuse_max`).
* "forget" of the authors' original server (decay toward unknown): ``l *= factor``
  (:func:`forget`).
"""

from __future__ import annotations

import math
from enum import StrEnum
from functools import lru_cache
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

SCALE: Final = 1000.0
"""Fixed-point units per nat of log-odds."""

MAX_STATE: Final = 16000
"""Largest magnitude of a stored cell or of one increment (16 nats: P within 1.1e-7 of 0/1)."""

DTYPE: Final = np.int16

DEFAULT_EPS0: Final = 0.001
"""Default clamp: cells stay in [eps0, 1 - eps0] (logit(0.999) = 6.9 nats)."""

MIN_EPS0: Final = 1.2e-7
"""Smallest eps0 whose clamp still fits inside MAX_STATE."""

FloatArray = npt.NDArray[np.floating]
Fixed = npt.NDArray[np.int16]


class Encoding(StrEnum):
    """Cell encodings of ISMs on the wire and of sub-map replies."""

    OCCUPANCY_I8 = "occupancy_i8"  # nav_msgs/OccupancyGrid: 0..100 percent, -1 unknown
    PROB_U8 = "prob_u8"  # p = v / 255 (no exact unknown: kept as it always was)
    PROB_F32 = "prob_f32"  # p in [0, 1]; NaN = unknown (no update)
    LOGODDS_I16 = "logodds_i16"  # this module's fixed point (reply only)
    PROB_U8_V2 = "prob_u8_v2"  # 0..254: p = v / 254 (127 = exactly 0.5); 255 = unknown


ENCODING_DTYPES: Final[dict[Encoding, np.dtype]] = {
    Encoding.OCCUPANCY_I8: np.dtype(np.int8),
    Encoding.PROB_U8: np.dtype(np.uint8),
    Encoding.PROB_F32: np.dtype(np.float32),
    Encoding.LOGODDS_I16: np.dtype(np.int16),
    Encoding.PROB_U8_V2: np.dtype(np.uint8),
}

OCCUPANCY_UNKNOWN: Final = -1

PROB_U8_V2_UNKNOWN: Final = 255
"""``prob_u8_v2``: the "no information" code (increment 0: the cell is left untouched)."""

PROB_U8_V2_MAX: Final = 254
"""``prob_u8_v2``: codes 0..254 are ``p = v / 254`` (so 127 is exactly 0.5, also increment 0)."""


def check_eps0(eps0: float) -> float:
    """Return ``eps0`` if it is a usable clamp, else raise ``ValueError``."""
    if not (MIN_EPS0 <= eps0 < 0.5):
        raise ValueError(f"eps0 must lie in [{MIN_EPS0}, 0.5), got {eps0!r}")
    return float(eps0)


def logit(p: npt.ArrayLike) -> FloatArray:
    """Natural log-odds ``log(p / (1 - p))`` in float64 (no clamping)."""
    p = np.asarray(p, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.log(p) - np.log1p(-p)


def sigmoid(l: npt.ArrayLike) -> FloatArray:
    """Inverse of :func:`logit`, numerically stable for large magnitudes."""
    l = np.asarray(l, dtype=np.float64)
    return 0.5 * (1.0 + np.tanh(0.5 * l))


def clamp_limits(eps0: float = DEFAULT_EPS0) -> tuple[int, int]:
    """Fixed-point bounds ``(lo, hi)`` of the clamp ``P in [eps0, 1 - eps0]``."""
    hi = round(float(logit(1.0 - check_eps0(eps0))) * SCALE)
    hi = min(hi, MAX_STATE)
    return -hi, hi


def to_fixed(l: npt.ArrayLike) -> Fixed:
    """Float nats -> int16 fixed point, rounded and limited to ``±MAX_STATE``."""
    with np.errstate(over="ignore"):  # |l| > 1.8e305 nats becomes inf, then the clip bound
        scaled = np.rint(np.asarray(l, dtype=np.float64) * SCALE)
    return np.clip(scaled, -MAX_STATE, MAX_STATE).astype(DTYPE)


def from_fixed(l: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """int fixed point -> float32 nats."""
    return (np.asarray(l, dtype=np.float32) / np.float32(SCALE)).astype(np.float32)


def prob_to_fixed(p: npt.ArrayLike, eps0: float = DEFAULT_EPS0) -> Fixed:
    """Probability -> fixed log-odds, clamped to ``[eps0, 1 - eps0]``."""
    p = np.clip(np.asarray(p, dtype=np.float64), eps0, 1.0 - eps0)
    return to_fixed(logit(p))


def fixed_to_prob(l: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Fixed log-odds -> probability (float32)."""
    return sigmoid(np.asarray(l, dtype=np.float64) / SCALE).astype(np.float32)


@lru_cache(maxsize=64)
def _lut(encoding: Encoding, eps0: float) -> Fixed:
    codes = np.arange(256)
    if encoding is Encoding.PROB_U8:
        table = prob_to_fixed(codes / 255.0, eps0)
    elif encoding is Encoding.PROB_U8_V2:
        p = np.minimum(codes, PROB_U8_V2_MAX) / float(PROB_U8_V2_MAX)
        table = np.where(codes == PROB_U8_V2_UNKNOWN, 0, prob_to_fixed(p, eps0)).astype(DTYPE)
    elif encoding is Encoding.OCCUPANCY_I8:
        signed = codes.astype(np.uint8).view(np.int8).astype(np.int64)
        valid = (signed >= 0) & (signed <= 100)
        table = np.where(valid, prob_to_fixed(np.clip(signed, 0, 100) / 100.0, eps0), 0)
        table = table.astype(DTYPE)
    else:
        raise ValueError(f"no lookup table for encoding {encoding!s}")
    table.setflags(write=False)
    return table


def increment_lut(encoding: Encoding | str, eps0: float = DEFAULT_EPS0) -> Fixed:
    """256-entry table: 8-bit ISM code (as its unsigned byte) -> fixed log-odds increment.

    ``occupancy_i8``: 0..100 percent -> ``logit(clip(v / 100))``; -1 (unknown) and the invalid
    codes 101..127, -128..-2 -> 0, i.e. the cell is left untouched (the codec rejects invalid
    codes before they get here).  ``prob_u8``: ``logit(clip(v / 255))``.  ``prob_u8_v2``:
    ``logit(clip(v / 254))`` for 0..254 (127 -> exactly 0), 255 (unknown) -> 0.
    """
    return _lut(Encoding(encoding), check_eps0(eps0))


def increments(
    data: npt.NDArray, encoding: Encoding | str, eps0: float = DEFAULT_EPS0
) -> Fixed:
    """Turn an ISM's cells into fixed log-odds increments (0 = no information)."""
    encoding = Encoding(encoding)
    if encoding is Encoding.PROB_F32:
        p = np.asarray(data, dtype=np.float32)
        unknown = np.isnan(p)
        if unknown.any():  # NaN is "no information": increment 0, the cell is untouched
            return np.where(unknown, DTYPE(0), prob_to_fixed(np.where(unknown, 0.5, p), eps0))
        return prob_to_fixed(p, eps0)
    if encoding is Encoding.LOGODDS_I16:
        return np.clip(data, -MAX_STATE, MAX_STATE).astype(DTYPE)
    # Bring the codes to the encoding's own 8-bit dtype first: viewing a wider integer array
    # (e.g. numpy's default int64) as bytes would index the table with every byte of it.
    codes = np.ascontiguousarray(data, dtype=ENCODING_DTYPES[encoding]).view(np.uint8)
    lut = increment_lut(encoding, eps0)
    if codes.ndim == 2 and codes.size:
        # Once per ISM cell: OpenCV's table lookup is ~3x faster than numpy's fancy indexing.
        return np.asarray(cv2.LUT(codes, lut), dtype=DTYPE)
    return lut[codes]


def bayes_update(state: Fixed, inc: Fixed, limits: tuple[int, int]) -> None:
    """Eq. 1 in log-odds, in place: ``state = clamp(state + inc)``.

    ``state`` and ``inc`` are int16 of the same shape (a warped patch is rounded before it gets
    here, :func:`sogm_service.core.resample.tile_patches`); ``limits`` from
    :func:`clamp_limits`.  Cells with ``inc == 0`` (unknown) are unchanged because they were
    already inside the clamp.
    """
    if state.ndim == 2 and state.strides[1] == state.itemsize:
        # |state + inc| <= 32000: OpenCV's saturating int16 add never saturates here, so it is
        # the exact sum; it is ~1.5x faster than numpy's on the strided views of an ISM (a
        # tile's part of a wider ISM).  OpenCV writes views with contiguous rows in place;
        # anything it had to copy is copied back.  (Only 2-D: OpenCV reads a 1-D array of up
        # to 4 values as a scalar.)
        out = cv2.add(state, inc, dst=state)
        if out is not state:
            np.copyto(state, out)
    else:
        np.add(state, inc, out=state)
    # int16 bounds: with Python ints numpy checks their range on every call (~1.3 us a tile).
    np.clip(state, DTYPE(limits[0]), DTYPE(limits[1]), out=state)


def fuse_bayes(stack: Fixed) -> npt.NDArray[np.int32]:
    """Eq. 6, super-Bayesian independent opinion pool over axis 0, as int32 fixed log-odds.

    ``P_B = 1 / (1 + prod_n (1 - P_n) / P_n)`` is ``sigmoid(sum_n l_n)``.
    """
    return np.sum(stack, axis=0, dtype=np.int32)


def fuse_max(stack: Fixed) -> Fixed:
    """Eq. 6, max pooling ``P_M = max_n P_n`` over axis 0, over the layers that observed the
    cell (logit is monotone, so it is a max of log-odds).

    A layer with no evidence in a cell (log-odds exactly 0, as an absent plane, an unknown ISM
    cell and a fully forgotten one are) has no opinion there: the cell is occupied when any
    layer that observed it says occupied, free when the layers that observed it say free,
    and unknown (0) only when no layer did.  Plain ``max_n`` would let one layer's unknown
    (``P = 0.5``) outvote every other layer's free: a fleet whose robots write their own
    layers would then see free space only where every robot looked.

    One pass per layer and no mask of the stack: the plain max ``hi`` is the answer wherever
    it is positive; where it is not, every layer is <= 0 and the max of the same bits read as
    ``uint16`` ranks 0 lowest and the negatives by their value (-1 highest), so it is the
    largest observed value, or 0 when no layer observed the cell.
    """
    hi = np.max(stack, axis=0)
    observed_max = np.max(stack.view(np.uint16), axis=0).view(DTYPE)
    take_hi = np.greater(hi, 0).view(np.int8).astype(DTYPE)
    np.negative(take_hi, out=take_hi)  # all bits set where hi > 0
    # observed_max ^ ((observed_max ^ hi) & take_hi): hi where hi > 0, else observed_max
    np.bitwise_xor(hi, observed_max, out=hi)
    np.bitwise_and(hi, take_hi, out=hi)
    np.bitwise_xor(hi, observed_max, out=hi)
    return hi


def forget(state: Fixed, factor: float) -> None:
    """Decay toward unknown in place: ``l *= factor`` with ``0 <= factor <= 1``."""
    if not 0.0 <= factor <= 1.0:
        raise ValueError(f"forget factor must lie in [0, 1], got {factor!r}")
    np.copyto(state, np.rint(state * np.float32(factor)).astype(DTYPE))


def weightless_age(half_life: float, magnitude: int) -> float:
    """The age (s) past which a layer forgetting with ``half_life`` keeps nothing of evidence
    of at most ``magnitude`` fixed-point units: decay is ``trunc(l * 0.5 ** (age / h))``,
    which is 0 for every ``|l| <= magnitude`` once ``0.5 ** (age / h) * magnitude < 1``,
    i.e. ``age > h * log2(magnitude)`` (12.8 half-lives at the default clamp)."""
    if not (half_life > 0 and math.isfinite(half_life)):
        raise ValueError(f"half-life must be positive and finite, got {half_life!r}")
    return float(half_life) * math.log2(max(int(magnitude), 1))


def _encode_direct(l: npt.NDArray, encoding: Encoding) -> npt.NDArray:
    """The definition of each reply encoding (what the tables below are built from)."""
    p = fixed_to_prob(l)
    if encoding is Encoding.PROB_F32:
        return p
    if encoding is Encoding.PROB_U8:
        return np.rint(p * 255.0).astype(np.uint8)
    if encoding is Encoding.PROB_U8_V2:
        v2 = np.rint(p * float(PROB_U8_V2_MAX)).astype(np.uint8)
        v2[l == 0] = PROB_U8_V2_UNKNOWN
        return v2
    occ = np.rint(p * 100.0).astype(np.int8)
    occ[l == 0] = OCCUPANCY_UNKNOWN
    return occ


@lru_cache(maxsize=8)
def _encode_table(encoding: Encoding) -> npt.NDArray:
    """Every int16 log-odds value's encoding, indexed by its bit pattern as uint16 (64 Ki).

    A reply of 4 x 256 x 256 cells then costs one gather instead of a float64 sigmoid through
    several temporaries (about 4x faster here), with identical results.
    """
    values = np.arange(65536, dtype=np.uint16).view(np.int16)  # 0..32767, -32768..-1
    table = _encode_direct(values, encoding)
    table.setflags(write=False)
    return table


def encode_fixed(l: npt.ArrayLike, encoding: Encoding | str) -> npt.NDArray:
    """Fixed log-odds (any int dtype) -> an output encoding for replies.

    ``occupancy_i8`` writes -1 and ``prob_u8_v2`` 255 where the cell is exactly unknown
    (l == 0).  Values beyond the
    int16 range (Eq. 6 sums of many layers) encode as the int16 extremes: P is 0 or 1 there
    at every output precision.
    """
    encoding = Encoding(encoding)
    l = np.asarray(l)
    l16 = l if l.dtype == np.int16 else np.clip(l, -32768, 32767).astype(np.int16)
    if encoding is Encoding.LOGODDS_I16:
        return np.maximum(l16, -32767)
    return np.take(_encode_table(encoding), np.ascontiguousarray(l16).view(np.uint16))


def decode_to_prob(data: npt.NDArray, encoding: Encoding | str) -> npt.NDArray[np.float32]:
    """Any encoding -> probability (unknown cells -> 0.5; NaN stays NaN in ``prob_f32``)."""
    encoding = Encoding(encoding)
    if encoding is Encoding.PROB_F32:
        return np.asarray(data, dtype=np.float32)
    if encoding is Encoding.PROB_U8:
        return (np.asarray(data, dtype=np.float32) / 255.0).astype(np.float32)
    if encoding is Encoding.PROB_U8_V2:
        v = np.asarray(data)
        p = v.astype(np.float32) / np.float32(PROB_U8_V2_MAX)
        return np.where(v == PROB_U8_V2_UNKNOWN, np.float32(0.5), p).astype(np.float32)
    if encoding is Encoding.LOGODDS_I16:
        return fixed_to_prob(data)
    occ = np.asarray(data, dtype=np.float32) / 100.0
    return np.where(np.asarray(data) == OCCUPANCY_UNKNOWN, 0.5, occ).astype(np.float32)
