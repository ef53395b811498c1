"""Display tile pictures: the cells one display tile needs (a sub-map or fused query at the
display tile's own resolution) and the PNG the page draws from them."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

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


def render(spec: TileSpec, data: np.ndarray) -> bytes:
    """Log-odds cells -> the PNG the page draws (map y up: row 0 is the tile's top)."""
    if data.ndim == 3 and data.shape[0] == 0:
        img = np.empty((*data.shape[1:], 3), np.uint8)
        img[:] = UNKNOWN_BGR
    elif spec.signature == "class":
        img = dominant_class_image(logodds.fixed_to_prob(data))
    else:
        cells = data[0] if data.ndim == 3 else data
        img = probability_image(logodds.fixed_to_prob(cells), unknown=cells == 0)
    ok, png = cv2.imencode(".png", img, _PNG)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()
