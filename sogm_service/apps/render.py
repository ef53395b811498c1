"""Pictures of maps for people (pure: arrays in, BGR uint8 images out; writing is the caller's).

Convention: free is white, occupied is black, and *unknown* (no evidence: log-odds 0) is a
distinct muted blue so that "never observed" never reads as "50 % occupied grey".
"""

from __future__ import annotations

import colorsys
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:  # only for annotations: drawing needs no Zenoh
    from sogm_service.service.client import GridResult
    from sogm_service.wire.messages import SupercellReply

UNKNOWN_BGR = (150, 110, 70)
_UNKNOWN_TOL = 0.5 / 255.0


def probability_image(p: npt.NDArray, unknown: npt.NDArray[np.bool_] | None = None,
                      scale: int = 1) -> npt.NDArray[np.uint8]:
    """``(H, W)`` probabilities -> BGR image; row 0 at the bottom (map y up)."""
    p = np.asarray(p, dtype=np.float32)
    if unknown is None:
        unknown = np.abs(p - 0.5) < _UNKNOWN_TOL
    grey = np.rint((1.0 - p) * 255.0).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=2)
    img[unknown] = UNKNOWN_BGR
    return _finish(img, scale)


def class_colors(n: int) -> npt.NDArray[np.uint8]:
    """``n`` well-separated BGR colours (golden-ratio hues)."""
    colors = []
    for k in range(n):
        r, g, b = colorsys.hsv_to_rgb((k * 0.618033988749895) % 1.0, 0.75, 0.95)
        colors.append((int(b * 255), int(g * 255), int(r * 255)))
    return np.array(colors, dtype=np.uint8).reshape(n, 3)


def dominant_class_image(stack: npt.NDArray, threshold: float = 0.5,
                         scale: int = 1) -> npt.NDArray[np.uint8]:
    """``(N, H, W)`` probabilities -> each cell coloured by its most likely layer.

    Cells where no layer exceeds ``threshold`` (with one u8 code of margin, because prob_u8
    cannot encode 0.5 exactly) are shown as unknown; the brightness follows the winner's p.
    """
    stack = np.asarray(stack, dtype=np.float32)
    colors = class_colors(stack.shape[0]).astype(np.float32)
    best = np.argmax(stack, axis=0)
    p = np.max(stack, axis=0)
    img = colors[best] * (0.4 + 0.6 * np.clip((p - threshold) / (1 - threshold), 0, 1))[..., None]
    out = img.astype(np.uint8)
    out[p <= threshold + _UNKNOWN_TOL * 2] = UNKNOWN_BGR
    return _finish(out, scale)


def _finish(img: npt.NDArray[np.uint8], scale: int) -> npt.NDArray[np.uint8]:
    img = np.ascontiguousarray(img[::-1])  # map y grows upward, image rows downward
    if scale > 1:
        img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    return img


def supercell_overlay(background: npt.NDArray, labels: npt.NDArray[np.int32],
                      centroids_cell: npt.NDArray, edges: list[tuple[int, int]],
                      dominant: npt.NDArray[np.int64], n_classes: int,
                      scale: int = 3) -> npt.NDArray[np.uint8]:
    """The topometric graph (paper Fig. 6) over a map picture.

    ``background``: ``(H, W)`` probabilities; ``labels``: the supercell image; borders in red,
    edges between adjacent supercells as lines, centroids as dots coloured by each supercell's
    dominant layer (-1: no evidence, grey).  Returned with map y up, like every picture here.
    """
    import cv2

    base = probability_image(background)[::-1]  # back to row 0 = v 0 for drawing
    img = np.ascontiguousarray(np.repeat(np.repeat(base, scale, 0), scale, 1))
    big = np.repeat(np.repeat(labels, scale, 0), scale, 1)
    border = np.zeros(big.shape, bool)
    border[:, 1:] |= big[:, 1:] != big[:, :-1]
    border[1:, :] |= big[1:, :] != big[:-1, :]
    img[border] = (40, 40, 220)
    pts = ((np.asarray(centroids_cell, dtype=np.float64) + 0.5) * scale).astype(np.int32)
    for a, b in edges:
        cv2.line(img, tuple(int(v) for v in pts[a]), tuple(int(v) for v in pts[b]),
                 (60, 160, 60), 1, cv2.LINE_AA)
    colors = class_colors(max(n_classes, 1))
    for k, (u, v) in enumerate(pts):
        d = int(dominant[k])
        color = (128, 128, 128) if d < 0 else tuple(int(c) for c in colors[d])
        cv2.circle(img, (int(u), int(v)), max(2, scale), color, -1, cv2.LINE_AA)
    return np.ascontiguousarray(img[::-1])


def draw_graph(reply: SupercellReply, fused: GridResult, scale: int = 3) -> npt.NDArray[np.uint8]:
    """The supercell graph of a reply (with labels) over a fused map of the same window."""
    assert reply.labels is not None, "ask the supercells query for its labels"
    g = fused.geometry
    to_cell = g.world_to_cell()
    xy = np.array([[n.x, n.y, 1.0] for n in reply.nodes]).reshape(-1, 3)
    cells = (to_cell @ xy.T).T[:, :2]
    edges = [(n.id, m) for n in reply.nodes for m in n.neighbors if n.id < m]
    dominant = np.array([int(np.argmax(n.mean_probability))
                         if max(n.mean_probability) > 0.51 else -1 for n in reply.nodes])
    return supercell_overlay(fused.probabilities(), reply.labels.array(), cells, edges,
                             dominant, len(reply.layers), scale)
