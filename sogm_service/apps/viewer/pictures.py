"""Display tile pictures: the cells one display tile needs (a sub-map or fused query at the
display tile's own resolution) and the PNG the page draws from them; the ``keepout`` and
``speed`` pictures paint nav2's filter masks over the map pooled by max."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from sogm_service.adapters.ros2.filters import FilterSpec, filter_classes, mask_cells
from sogm_service.apps.render import UNKNOWN_BGR, dominant_class_image, probability_image
from sogm_service.apps.viewer.tiles import TileSpec
from sogm_service.client.mapclient import MapClient
from sogm_service.core import logodds


def fetch(client: MapClient, spec: TileSpec) -> tuple[np.ndarray, list[str]]:
    """The cells of one display tile as log-odds: ``(N, P, P)`` or ``(P, P)`` (fused)."""
    cx, cy = spec.centre
    window: dict[str, Any] = dict(x=cx, y=cy, width=spec.span, height=spec.span,
                                  resolution=spec.resolution, encoding="logodds_i16")
    kind, _, rest = spec.signature.partition(":")
    if kind == "layer":
        r = client.submap(**window, layers=[rest])
    elif kind == "fused":
        method, _, names = rest.partition(":")
        r = client.fused(**window, method=method, layers=names.split(",") if names else None)
    else:
        r = client.submap(**window)
    return np.asarray(r.data), list(r.layers)


_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]


KEEPOUT_BGR = np.array((40, 40, 230), np.float32)  # red
SPEED_BGR = np.array((0, 170, 255), np.float32)  # amber, stronger the lower the limit


def mask_image(data: np.ndarray, layers: list[str], filters: FilterSpec,
               mask: str) -> np.ndarray:
    """The map pooled by max (Eq. 6, P_M) in grey, nav2's ``mask`` painted over it: kept-out
    cells red, speed-limited cells amber (the lower the limit, the stronger)."""
    stack = np.asarray(data, np.int16)
    base = logodds.fuse_max(stack)
    img = probability_image(logodds.fixed_to_prob(base), unknown=base == 0)[::-1]
    cells = mask_cells(filters, stack, layers, filter_classes(filters, layers)).get(mask)
    if cells is None:  # no such mask asked of this viewer: the map alone
        return np.ascontiguousarray(img[::-1])
    out = img.astype(np.float32)
    if mask == "keepout":
        hit, alpha = cells == 100, np.float32(0.7)
        out[hit] = (1 - alpha) * out[hit] + alpha * KEEPOUT_BGR
    else:
        hit = cells > 0
        a = (0.35 + 0.55 * (100 - cells[hit].astype(np.float32)) / 100)[:, None]
        out[hit] = (1 - a) * out[hit] + a * SPEED_BGR
    return np.ascontiguousarray(np.rint(out).astype(np.uint8)[::-1])


def render(spec: TileSpec, data: np.ndarray, layers: list[str] | None = None,
           filters: FilterSpec | None = None) -> bytes:
    """Log-odds cells -> the PNG the page draws (map y up: row 0 is the tile's top)."""
    if data.ndim == 3 and data.shape[0] == 0:
        img = np.empty((*data.shape[1:], 3), np.uint8)
        img[:] = UNKNOWN_BGR
    elif spec.signature in ("keepout", "speed"):
        img = mask_image(data, layers or [], filters or FilterSpec(), spec.signature)
    elif spec.signature == "class":
        img = dominant_class_image(logodds.fixed_to_prob(data))
    else:
        cells = data[0] if data.ndim == 3 else data
        img = probability_image(logodds.fixed_to_prob(cells), unknown=cells == 0)
    ok, png = cv2.imencode(".png", img, _PNG)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()
