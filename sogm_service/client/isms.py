"""ISMs on the client's side: the :class:`~sogm_service.wire.messages.IsmMessage` of a grid,
checked as the server will check it (:func:`build_ism`), and where a published ISM lies
(:class:`IsmFootprint`, read from its header fields by :func:`ism_footprint`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from sogm_service.core import logodds
from sogm_service.core.geometry import Pose2D
from sogm_service.wire import codec
from sogm_service.wire.errors import InvalidIsmError
from sogm_service.wire.messages import IsmMessage, PoseModel


def encoding_of(arr: npt.NDArray[Any]) -> str:
    """The ISM encoding an array's dtype implies; raises :class:`InvalidIsmError` for others."""
    if arr.dtype == np.uint8:
        return "prob_u8"
    if arr.dtype == np.int8:
        return "occupancy_i8"
    if np.issubdtype(arr.dtype, np.floating):
        return "prob_f32"
    raise InvalidIsmError(f"cannot infer an ISM encoding from dtype {arr.dtype}: use uint8 "
                          "(prob_u8), int8 (occupancy_i8) or float32 (prob_f32), or name "
                          "the encoding")


def build_ism(data: npt.NDArray[Any], *, resolution: float, origin: Pose2D | None = None,
              encoding: str | None = None, layer: str | None = None, frame: str = "map",
              stamp: float | None = None, robot: str | None = None) -> IsmMessage:
    """The :class:`IsmMessage` of a grid, checked as the server will check it; raises
    :class:`InvalidIsmError` (one line) for anything it would refuse or that would not mean
    what the array says.  ``stamp``: Unix time in seconds, default now (the time a layer that
    forgets weighs the ISM by)."""
    origin = origin or Pose2D()
    arr = np.ascontiguousarray(data)
    if arr.ndim != 2 or 0 in arr.shape:
        raise InvalidIsmError(f"an ISM is a 2-D grid (rows, columns); got shape {arr.shape}")
    enc = encoding or encoding_of(arr)
    try:
        dtype = logodds.ENCODING_DTYPES[logodds.Encoding(enc)]
    except ValueError:
        raise InvalidIsmError(f"unknown encoding {enc!r}: one of "
                              f"{', '.join(e.value for e in logodds.Encoding)}") from None
    if arr.dtype.kind not in "biuf":
        raise InvalidIsmError(f"dtype {arr.dtype} is not a number")
    with np.errstate(invalid="ignore", over="ignore"):
        cells = arr.astype(dtype.newbyteorder("<"))
        same = np.array_equal(cells.astype(np.float64), arr.astype(np.float64), equal_nan=True)
    if not same:
        raise InvalidIsmError(f"the {arr.dtype} values do not fit encoding {enc} ({dtype}) "
                              "without changing them: convert them first")
    try:
        return IsmMessage(layer=layer, frame=frame,
                          stamp=time.time() if stamp is None else stamp, robot=robot,
                          resolution=resolution,
                          origin=PoseModel(x=origin.x, y=origin.y, yaw=origin.yaw),
                          width=arr.shape[1], height=arr.shape[0], encoding=enc,
                          data=cells.tobytes())
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        where = ".".join(str(p) for p in err["loc"]) or "ism"
        raise InvalidIsmError(f"{where}: {err['msg']}") from None


@dataclass(frozen=True)
class IsmFootprint:
    """Where one ISM lies in its frame: the four corners of its grid (m), counter-clockwise
    from the origin corner of cell (0, 0)."""

    key: str
    robot: str | None
    layer: str | None
    frame: str
    stamp: float
    corners: tuple[tuple[float, float], ...]


def ism_footprint(key: str, payload: bytes) -> IsmFootprint | None:
    """The footprint of an ISM payload from its header fields, or ``None`` when they are
    missing or not finite (never raises)."""
    try:
        obj = codec.unpack(payload)
    except codec.DecodeError:
        return None
    if not isinstance(obj, dict):
        return None
    origin = obj.get("origin") or {}
    try:
        res = float(obj["resolution"])
        w, h = obj["width"], obj["height"]
        x, y, yaw = (float(origin.get(k, 0.0)) for k in ("x", "y", "yaw"))
        stamp = float(obj.get("stamp", 0.0))
    except (KeyError, TypeError, ValueError, AttributeError):
        return None
    if not (isinstance(w, int) and isinstance(h, int) and 0 < w <= 1 << 20
            and 0 < h <= 1 << 20 and res > 0
            and all(math.isfinite(v) for v in (res, x, y, yaw, stamp))):
        return None
    c, s = math.cos(yaw), math.sin(yaw)
    corners = tuple((x + c * u - s * v, y + s * u + c * v)
                    for u, v in ((0.0, 0.0), (w * res, 0.0), (w * res, h * res), (0.0, h * res)))
    robot, layer = obj.get("robot"), obj.get("layer")
    frame = obj.get("frame", "map")
    return IsmFootprint(key, robot if isinstance(robot, str) else None,
                        layer if isinstance(layer, str) else None,
                        frame if isinstance(frame, str) else "map", stamp, corners)
