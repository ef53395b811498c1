"""SEVDS against OpenCV's SEEDS on the same input (the ``sevds`` row of ``sogm-service bench``)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.bench.core import best_time
from sogm_service.core.sevds.segment import SevdsParams, sevds


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
        sevds_s = best_time(lambda s=stack: sevds(s, p), repeats)  # type: ignore[misc]
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
            seeds_s = best_time(
                lambda i=img, c=count: _seeds_run(  # type: ignore[misc]
                    i, c, p.levels, p.bins, p.iterations), repeats)
            row["seeds_s"] = seeds_s
            row["ratio_sevds_over_seeds"] = sevds_s / seeds_s
        rows.append(row)
    return rows
