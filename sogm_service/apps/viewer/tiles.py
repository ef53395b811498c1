"""Which pictures the page needs: display tiles on a pyramid over the map's tile lattice (pure).

The page shows the map as square *display tiles* of at most :data:`DISPLAY_PX` pixels.  At level
``k`` one display tile ``(k, a, b)`` covers ``2^k x 2^k`` lattice tiles, i.e. the square
``[a S_k, (a+1) S_k) x [b S_k, (b+1) S_k)`` with ``S_k = T res 2^k`` (``T`` the map's tile size,
``res`` its resolution), sampled at ``S_k / P`` metres per pixel (``P = min(T, DISPLAY_PX)``).
Level 0 at ``T <= DISPLAY_PX`` is the map itself, cell for cell.

The level is the finest one whose pixels are at least one screen pixel, so a view never needs
more than about ``(W/P + 2) x (H/P + 2)`` tiles whatever the zoom (60 for a 1920 x 1080 screen),
and only display tiles over a *known* lattice tile are asked for: the work one browser can cause
on the map server is bounded by its screen, not by the map.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

DISPLAY_PX = 256
"""Largest side of a display tile in pixels."""

MAX_LEVEL = 16
"""Coarsest pyramid level (2^16 lattice tiles a side: far beyond any real map)."""

MAX_TILES_PER_VIEW = 96
"""Display tiles one view may ask for in one refresh (more: the nearest to the centre)."""

MODES = ("layer", "class", "fused", "keepout", "speed")
"""``keepout`` and ``speed``: nav2's filter masks over the map (the viewer's ``--keepout`` and
``--speed``, the rules of :mod:`sogm_service.adapters.ros2.filters`)."""
METHODS = ("bayes", "max")


@dataclass(frozen=True, slots=True)
class Lattice:
    """The map's tile lattice as the page needs it: resolution (m) and tile size (cells)."""

    resolution: float
    tile_size: int

    @property
    def span(self) -> float:
        """Side of one lattice tile in metres."""
        return self.resolution * self.tile_size

    @property
    def pixels(self) -> int:
        """Side of a display tile in pixels."""
        return min(self.tile_size, DISPLAY_PX)

    def level_span(self, level: int) -> float:
        return self.span * (1 << level)

    def level_for(self, px_per_m: float) -> int:
        """The finest level whose display pixels cover at least one screen pixel."""
        if not (math.isfinite(px_per_m) and px_per_m > 0):
            return MAX_LEVEL
        pixel_m = self.span / self.pixels  # level 0
        screen_px_per_display_px = px_per_m * pixel_m
        if screen_px_per_display_px >= 1.0:
            return 0
        level = math.ceil(math.log2(1.0 / screen_px_per_display_px) - 1e-9)
        return max(0, min(MAX_LEVEL, level))


@dataclass(frozen=True, slots=True)
class View:
    """What one page shows: a metric box, its zoom, and which picture of the map."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    px_per_m: float
    mode: str = "class"
    layer: str | None = None
    layers: tuple[str, ...] = ()
    method: str = "bayes"

    def signature(self) -> str:
        """Identifies the picture (not the box): tiles of equal signatures are interchangeable."""
        if self.mode == "layer":
            return f"layer:{self.layer}"
        if self.mode == "fused":
            return f"fused:{self.method}:{','.join(self.layers)}"
        if self.mode in ("keepout", "speed"):
            return self.mode
        return "class"


class ViewError(ValueError):
    """A view message from the page that cannot be used (``code`` says why)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


_MAX_EXTENT_M = 1e7  # a view wider than 10,000 km is not a view of a map


def parse_view(msg: dict[str, object], known_layers: list[str]) -> View:
    """A ``view`` message from the page -> a :class:`View`, or :class:`ViewError`."""
    try:
        box = [float(msg[k]) for k in ("xmin", "ymin", "xmax", "ymax")]  # type: ignore[arg-type]
        zoom = float(msg["px_per_m"])  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError):
        raise ViewError("bad_view", "a view needs numbers xmin, ymin, xmax, ymax, px_per_m") \
            from None
    if not all(math.isfinite(v) for v in [*box, zoom]) or zoom <= 0:
        raise ViewError("bad_view", "view numbers must be finite and the zoom positive")
    xmin, ymin, xmax, ymax = box
    if not (xmin < xmax and ymin < ymax) or max(xmax - xmin, ymax - ymin) > _MAX_EXTENT_M \
            or max(abs(v) for v in box) > _MAX_EXTENT_M:
        raise ViewError("bad_view", "the view box is empty or absurdly large")
    mode = msg.get("mode", "class")
    if mode not in MODES:
        raise ViewError("bad_mode", f"mode must be one of {MODES}")
    method = msg.get("method", "bayes")
    if method not in METHODS:
        raise ViewError("bad_method", f"method must be one of {METHODS}")
    layer = msg.get("layer")
    raw_layers = msg.get("layers") or []
    if not isinstance(raw_layers, list) or not all(isinstance(n, str) for n in raw_layers):
        raise ViewError("bad_layers", "layers must be a list of names")
    layers = tuple(n for n in known_layers if n in raw_layers)  # map order, known names only
    if mode == "layer" and layer not in known_layers:
        raise ViewError("unknown_layer", f"unknown layer {layer!r}")
    if mode == "fused" and not layers:
        layers = tuple(known_layers)
    return View(xmin, ymin, xmax, ymax, zoom, str(mode),
                str(layer) if mode == "layer" else None, layers if mode == "fused" else (),
                str(method))


@dataclass(frozen=True, slots=True)
class TileSpec:
    """One display tile of one picture: everything needed to ask the map server for it."""

    signature: str
    level: int
    a: int
    b: int
    x0: float
    y0: float
    span: float
    pixels: int

    @property
    def key(self) -> str:
        """The page's name for this tile."""
        return f"{self.signature}|{self.level}|{self.a}|{self.b}"

    @property
    def centre(self) -> tuple[float, float]:
        return self.x0 + self.span / 2, self.y0 + self.span / 2

    @property
    def resolution(self) -> float:
        return self.span / self.pixels


def known_at_level(known: Iterable[tuple[int, int]], level: int) -> set[tuple[int, int]]:
    """Display tiles of ``level`` that hold at least one known lattice tile."""
    return {(i >> level, j >> level) for i, j in known}  # >> floors negatives too


def visible_tiles(view: View, lattice: Lattice, known_display: set[tuple[int, int]],
                  level: int, limit: int = MAX_TILES_PER_VIEW) -> list[TileSpec]:
    """The known display tiles of ``level`` that meet the view, nearest to its centre first."""
    span = lattice.level_span(level)
    a0, a1 = math.floor(view.xmin / span), math.floor(view.xmax / span)
    b0, b1 = math.floor(view.ymin / span), math.floor(view.ymax / span)
    if (a1 - a0 + 1) * (b1 - b0 + 1) <= 4 * len(known_display):
        candidates = [(a, b) for a in range(a0, a1 + 1) for b in range(b0, b1 + 1)
                      if (a, b) in known_display]
    else:  # a huge box over a small map: walk the known tiles instead of the box
        candidates = [(a, b) for a, b in known_display if a0 <= a <= a1 and b0 <= b <= b1]
    cx, cy = (view.xmin + view.xmax) / 2, (view.ymin + view.ymax) / 2
    candidates.sort(key=lambda ab: ((ab[0] + 0.5) * span - cx) ** 2
                    + ((ab[1] + 0.5) * span - cy) ** 2)
    sig = view.signature()
    return [TileSpec(sig, level, a, b, a * span, b * span, span, lattice.pixels)
            for a, b in candidates[:limit]]
