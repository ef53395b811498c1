"""Pictures of maps for people (pure: arrays in, BGR uint8 images out; writing is the caller's).

Convention: free is white, occupied is black, and *unknown* (no evidence: log-odds 0) is a
distinct muted blue so that "never observed" never reads as "50 % occupied grey".
"""

from __future__ import annotations

import colorsys
import math
import os
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from sogm_service.core.sevds.supercells import FREE, node_evidence

if TYPE_CHECKING:  # only for annotations: drawing needs no Zenoh
    from sogm_service.client.results import GridResult
    from sogm_service.wire.queries import SupercellReply

UNKNOWN_BGR = (150, 110, 70)
FREE_NODE_BGR = (0, 140, 255)  # a supercell node observed free: orange
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


def palette_hex(n: int) -> list[str]:
    """`class_colors` as #rrggbb: a page's legend in the colours of its tiles."""
    return ["#{2:02x}{1:02x}{0:02x}".format(*map(int, c)) for c in class_colors(n)]


UNKNOWN_HEX = "#{2:02x}{1:02x}{0:02x}".format(*UNKNOWN_BGR)

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
    edges between adjacent supercells as lines, nodes as dots coloured by each supercell's
    evidence (``dominant``: its occupied layer, or ``FREE`` orange, or ``UNKNOWN`` grey, as
    :func:`sogm_service.core.sevds.supercells.node_evidence`).  Returned with map y up, like
    every picture here.
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
        color = tuple(int(c) for c in colors[d]) if d >= 0 else \
            (FREE_NODE_BGR if d == FREE else (128, 128, 128))
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
    dominant = node_evidence(np.array([n.mean_probability for n in reply.nodes],
                                      dtype=np.float64).reshape(len(reply.nodes), -1))
    return supercell_overlay(fused.probabilities(), reply.labels.array(), cells, edges,
                             dominant, len(reply.layers), scale)


# --------------------------------------------------------------------------- readable figures
#
# Every PNG the CLI and the demo write goes through :func:`save_map_png`: the picture above in
# a matplotlib figure with the map axes in metres, a scale bar, a legend (the unknown colour
# included) and robot markers with their heading.  The picture itself is drawn nearest-
# neighbour into at least MIN_PICTURE_PX pixels on its long side, so a 60 x 40 cell sub-map
# is readable.  matplotlib is the ``plots`` extra: without it the bare picture is written
# (upsampled all the same) and one log line says how to get the rest.

MIN_PICTURE_PX = 512
Robot = tuple[str, float, float, float | None]
"""A robot marker: name, x, y (m, map frame) and heading (rad) when known."""
LegendEntry = tuple[str, tuple[int, int, int]]
"""A legend line: label and BGR colour."""

PROBABILITY_LEGEND: list[LegendEntry] = [
    ("free (p = 0)", (255, 255, 255)), ("occupied (p = 1)", (0, 0, 0)),
    ("unknown (never observed)", UNKNOWN_BGR)]


def _have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        import logging

        logging.getLogger(__name__).warning(
            "pictures without legend, axes and scale bar: install matplotlib "
            "(pip install 'sogm-service[plots]')")
        return False
    return True


def upsample(img: npt.NDArray[np.uint8], min_px: int = MIN_PICTURE_PX) -> npt.NDArray[np.uint8]:
    """Nearest-neighbour upsampling by an integer factor to at least ``min_px`` on the long
    side (never down)."""
    k = max(1, -(-min_px // max(img.shape[0], img.shape[1], 1)))
    return np.ascontiguousarray(np.repeat(np.repeat(img, k, axis=0), k, axis=1)) if k > 1 \
        else img


def _nice_length(span_m: float) -> float:
    """A round scale-bar length of about a fifth of ``span_m``."""
    target = max(span_m / 5.0, 1e-6)
    mag = 10 ** np.floor(np.log10(target))
    return float(max(s * mag for s in (1, 2, 5) if s * mag <= target * 1.0001))


def save_map_png(path: str | os.PathLike[str], img: npt.NDArray[np.uint8], geometry: object, *,
                 title: str = "", legend: list[LegendEntry] | None = None,
                 robots: list[Robot] | None = None, note: str = "") -> str:
    """Write ``img`` (BGR, map y up as every picture here: row 0 at the top) of a grid with
    ``geometry`` (a :class:`~sogm_service.core.geometry.GridGeometry`) as a readable PNG.

    Axes are metres of the map frame when the grid is not rotated, else of the window's own
    frame (its heading in the title); robots are drawn as arrows (or dots without heading)."""
    import cv2

    out = os.fspath(path)
    if not _have_matplotlib():
        cv2.imwrite(out, upsample(img))
        return out
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    g: Any = geometry
    r, w, h = float(g.resolution), int(g.width), int(g.height)
    yaw = float(g.origin.yaw)
    rotated = abs(math.remainder(yaw, 2 * math.pi)) > 1e-6
    x0, y0 = (0.0, 0.0) if rotated else (float(g.origin.x), float(g.origin.y))
    extent = (x0, x0 + w * r, y0, y0 + h * r)
    # The drawing area: the long side at least MIN_PICTURE_PX pixels (at 100 dpi).
    dpi = 100
    scale = max(MIN_PICTURE_PX / max(w, h), 1.0)
    ax_w, ax_h = max(w * scale, 64) / dpi, max(h * scale, 64) / dpi
    left, right, bottom, top = 0.9, 2.6, 0.7, 0.5
    fig = Figure(figsize=(ax_w + left + right, ax_h + bottom + top), dpi=dpi)
    FigureCanvasAgg(fig)
    fw, fh = fig.get_size_inches()
    ax = fig.add_axes((left / fw, bottom / fh, ax_w / fw, ax_h / fh))
    ax.imshow(img[..., ::-1], extent=extent, interpolation="nearest", origin="upper")
    ax.set_xlabel("window x (m)" if rotated else "map x (m)")
    ax.set_ylabel("window y (m)" if rotated else "map y (m)")
    heading = f" (window heading {math.degrees(yaw):.1f} deg)" if rotated else ""
    ax.set_title((title + heading).strip(), fontsize=10)
    length = _nice_length(w * r)
    ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower right",
                                  pad=0.4, color="crimson", frameon=True, size_vertical=0,
                                  label_top=True))
    handles: list[Any] = [Patch(facecolor=(c[2] / 255.0, c[1] / 255.0, c[0] / 255.0),
                                edgecolor="0.4", label=n)
                          for n, c in (legend or PROBABILITY_LEGEND)]
    if robots:
        c, s = math.cos(yaw), math.sin(yaw)
        ox, oy = float(g.origin.x), float(g.origin.y)
        arrow = max(w, h) * r / 25.0
        for name, x, y, heading_rad in robots:
            u, v = (x, y) if not rotated else (c * (x - ox) + s * (y - oy) + 0.0,
                                               -s * (x - ox) + c * (y - oy))
            if not (extent[0] <= u <= extent[1] and extent[2] <= v <= extent[3]):
                continue
            ax.plot([u], [v], "o", ms=6, mfc="crimson", mec="white", mew=1.2)
            if heading_rad is not None:
                a = heading_rad - (yaw if rotated else 0.0)
                ax.annotate("", xy=(u + arrow * math.cos(a), v + arrow * math.sin(a)),
                            xytext=(u, v), arrowprops={"arrowstyle": "-|>", "color": "crimson",
                                                       "lw": 1.8})
            ax.annotate(name, (u, v), xytext=(5, 5), textcoords="offset points", fontsize=8,
                        color="crimson")
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], marker="o", ls="", mfc="crimson", mec="white",
                              label="robot (arrow: heading)"))
    fig.legend(handles=handles, loc="upper left", bbox_to_anchor=((left + ax_w + 0.15) / fw,
                                                                    (bottom + ax_h) / fh),
               fontsize=8, frameon=False)
    if note:
        fig.text((left + ax_w + 0.15) / fw, bottom / fh, note, fontsize=7, va="bottom",
                 wrap=True)
    fig.savefig(out, dpi=dpi)
    return out


def save_grid_png(path: str | os.PathLike[str], p: npt.NDArray, geometry: object, *,
                  title: str = "", robots: list[Robot] | None = None) -> str:
    """One layer (or a fused map) of probabilities: free white, occupied black, unknown blue."""
    return save_map_png(path, probability_image(p), geometry, title=title,
                        legend=PROBABILITY_LEGEND, robots=robots)


def class_legend(layers: list[str]) -> list[LegendEntry]:
    colors = class_colors(max(len(layers), 1))
    out: list[LegendEntry] = [(name.rsplit("/", 1)[-1] if name.count("/") else name,
                               (int(c[0]), int(c[1]), int(c[2])))
                              for name, c in zip(layers, colors, strict=False)]
    return [*out, ("unknown (no class above p = 0.5)", UNKNOWN_BGR)]


def save_classes_png(path: str | os.PathLike[str], stack: npt.NDArray, geometry: object,
                     layers: list[str], *, title: str = "most likely class",
                     robots: list[Robot] | None = None) -> str:
    """Each cell in the colour of its most likely layer (brighter: more certain)."""
    return save_map_png(path, dominant_class_image(stack), geometry, title=title,
                        legend=class_legend(layers), robots=robots)


def save_graph_png(path: str | os.PathLike[str], reply: SupercellReply, fused: GridResult,
                   robots: list[Robot] | None = None) -> str:
    """The supercell graph over the fused map of its window, with its legend."""
    img = draw_graph(reply, fused, scale=4)
    legend = [*PROBABILITY_LEGEND[:2], ("supercell border", (40, 40, 220)),
              ("edge between neighbours", (60, 160, 60)),
              *[(f"node: {name}", c) for name, c in class_legend(list(reply.layers))[:-1]],
              ("node: free floor (observed, no layer occupied)", FREE_NODE_BGR),
              ("node without evidence (unknown)", (128, 128, 128)), PROBABILITY_LEGEND[2]]
    return save_map_png(path, img, fused.geometry,
                        title=f"supercells: {len(reply.nodes)} nodes (SEVDS)", legend=legend,
                        robots=robots)
