"""The figures of the paper's evaluation: metric curves (Fig. 12-16) and segmentations (Fig. 11).

Metric curves through matplotlib (the ``plots`` extra: :func:`save_line_plot`); without it the
OpenCV drawing :func:`line_plot` is written instead.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.eval import metrics
from sogm_service.eval.metrics import METRIC_TITLES, METRICS
from sogm_service.eval.scenes import Labels, Scene

COLOURS: tuple[tuple[int, int, int], ...] = (
    (40, 40, 220), (30, 150, 30), (200, 120, 20), (0, 170, 230), (170, 60, 170), (90, 90, 90))


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values covering ``[lo, hi]``."""
    span = hi - lo if hi > lo else max(abs(hi), 1.0)
    raw = span / n
    mag = 10 ** np.floor(np.log10(raw))
    step = float(min((s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= 0.999 * raw), default=raw))
    start = np.floor(lo / step) * step
    return [float(t) for t in np.arange(start, hi + step * 0.5, step) if lo - 1e-12 <= t]


def line_plot(series: Mapping[str, tuple[Sequence[float], Sequence[float]]], title: str,
              xlabel: str, ylabel: str, size: tuple[int, int] = (720, 460)) -> npt.NDArray:
    """A simple line chart (axes, ticks, markers, legend) as a BGR image, drawn with OpenCV."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 80, 170, 40, 60
    xs = np.concatenate([np.asarray(x, float) for x, _ in series.values()])
    ys = np.concatenate([np.asarray(y, float) for _, y in series.values()])
    x0, x1 = float(xs.min()), float(xs.max())
    y0, y1 = float(ys.min()), float(ys.max())
    pad = 0.05 * (y1 - y0 if y1 > y0 else max(abs(y1), 1e-3))
    y0, y1 = y0 - pad, y1 + pad
    x1 = x1 if x1 > x0 else x0 + 1.0

    def px(x: float, y: float) -> tuple[int, int]:
        return (round(left + (x - x0) / (x1 - x0) * (w - left - right)),
                round(h - bottom - (y - y0) / (y1 - y0) * (h - top - bottom)))

    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.rectangle(img, (left, top), (w - right, h - bottom), (0, 0, 0), 1)
    for t in _nice_ticks(y0, y1):
        if y0 <= t <= y1:
            p = px(x0, t)
            cv2.line(img, (left - 5, p[1]), (w - right, p[1]), (225, 225, 225), 1)
            cv2.line(img, (left - 5, p[1]), (left, p[1]), (0, 0, 0), 1)
            cv2.putText(img, f"{t:.4g}", (5, p[1] + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for t in _nice_ticks(x0, x1, 6):
        if x0 <= t <= x1:
            p = px(t, y0)
            cv2.line(img, (p[0], h - bottom), (p[0], h - bottom + 5), (0, 0, 0), 1)
            cv2.putText(img, f"{t:.4g}", (p[0] - 14, h - bottom + 20), font, 0.4, (0, 0, 0), 1,
                        cv2.LINE_AA)
    cv2.putText(img, title, (left, 25), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, ((w - right + left) // 2 - 60, h - 15), font, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    cv2.putText(img, ylabel, (5, top - 8), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for k, (name, (x, y)) in enumerate(series.items()):
        colour = COLOURS[k % len(COLOURS)]
        pts = [px(float(a), float(b)) for a, b in zip(x, y, strict=True)]
        for p, q in itertools.pairwise(pts):
            cv2.line(img, p, q, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
        ly = top + 20 + 22 * k
        cv2.line(img, (w - right + 15, ly), (w - right + 45, ly), colour, 2, cv2.LINE_AA)
        cv2.putText(img, name, (w - right + 52, ly + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def metric_plots(rows: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    """One PNG per metric: scene-mean value over the mean number of superpixels (Fig. 12-16)."""
    files = []
    for m in METRICS:
        series: dict[str, tuple[list[float], list[float]]] = {}
        for alg in dict.fromkeys(r["algorithm"] for r in rows):
            sel = [r for r in rows if r["algorithm"] == alg]
            blocks = sorted({r["block"] for r in sel}, reverse=True)
            xs = [float(np.mean([r["superpixels"] for r in sel if r["block"] == b]))
                  for b in blocks]
            ys = [float(np.mean([r[m] for r in sel if r["block"] == b])) for b in blocks]
            series[alg] = (xs, ys)
        path = out_dir / f"{m}.png"
        save_line_plot(path, series, METRIC_TITLES[m], "number of superpixels", m)
        files.append(path)
    return files


def _composite(stack: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    """The first three layers as a BGR picture (layer 0 -> red, 1 -> green, 2 -> blue)."""
    rgb = np.zeros((*stack.shape[1:], 3), np.float32)
    k = min(3, stack.shape[0])
    rgb[..., :k] = stack[:k].transpose(1, 2, 0)
    return np.ascontiguousarray(np.rint(rgb[..., ::-1] * 255).astype(np.uint8))


def _majority_image(labels: Labels, classes: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """Each superpixel painted with the grey of its majority ground-truth class (Fig. 11 top)."""
    s, ns = np.unique(labels, return_inverse=True)
    nc = int(classes.max()) + 1
    table = np.bincount(ns.ravel() * nc + classes.ravel(), minlength=s.size * nc)
    major = table.reshape(s.size, nc).argmax(axis=1)
    grey = np.linspace(40, 230, nc).astype(np.uint8)
    return np.repeat(grey[major[ns.reshape(labels.shape)]][..., None], 3, axis=2)


def segmentation_figure(scene: Scene, labelled: dict[str, Labels]) -> npt.NDArray[np.uint8]:
    """Paper Fig. 11: per algorithm, class-majority colouring (top) and red boundaries (bottom);
    the first column shows the ground truth and the SOGM composite."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    h, w = scene.classes.shape
    grey = np.linspace(40, 230, len(scene.class_names)).astype(np.uint8)
    tops = [np.repeat(grey[scene.classes][..., None], 3, axis=2)]
    bottoms = [_composite(scene.stack)]
    names = ["ground truth"]
    for name, lab in labelled.items():
        tops.append(_majority_image(lab, scene.classes))
        edge = _composite(scene.stack)
        edge[metrics.boundary_map(lab)] = (0, 0, 255)
        bottoms.append(edge)
        names.append(name)
    gap = np.full((h, 6, 3), 255, np.uint8)
    rows = [np.hstack([x for t in tops for x in (t, gap)][:-1]),
            np.hstack([x for b in bottoms for x in (b, gap)][:-1])]
    band = np.full((26, rows[0].shape[1], 3), 255, np.uint8)
    for k, name in enumerate(names):
        cv2.putText(band, name, (k * (w + 6) + 4, 18), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([band, rows[0], np.full((6, rows[0].shape[1], 3), 255, np.uint8), rows[1]])


# --------------------------------------------------------------------------- driver




def save_line_plot(path: Path, series: Mapping[str, tuple[Sequence[float], Sequence[float]]],
                   title: str, xlabel: str, ylabel: str) -> Path:
    """A metric curve per algorithm (markers, grid, legend) through matplotlib; the OpenCV
    drawing when matplotlib is not installed."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        cv2.imwrite(str(path), line_plot(series, title, xlabel, ylabel))
        return path
    fig = Figure(figsize=(7.2, 4.6), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    markers = itertools.cycle("osD^vP*X")
    for name, (xs, ys) in series.items():
        ax.plot(list(xs), list(ys), marker=next(markers), ms=4, lw=1.5, label=name)
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path)
    return path
