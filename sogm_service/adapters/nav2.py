"""nav2 map files: ``map.yaml`` + ``map.pgm`` as nav2's ``map_server`` reads them.

Writing (:func:`export_nav2`): mode ``trinary``, ``negate: 0``, ``occupied_thresh: 0.65``,
``free_thresh: 0.25`` (nav2's defaults), ``origin: [x, y, yaw]`` the pose of the lower-left
corner of the lower-left pixel, i.e. of grid cell (0, 0).  The image is an 8-bit binary PGM
(P5) whose **top row is the grid's last row** (largest y): map_server puts image row ``r`` into
grid row ``height - 1 - r``.  Pixels: occupied 0, free 254, unknown 128.

Why unknown is 128 and not map_saver's 205: map_server reads a pixel as
``occ = 1 - value / 255`` (negate 0) and, in trinary mode, gives occupied when
``occ > occupied_thresh``, free when ``occ < free_thresh``, unknown otherwise.  205 is
``occ = 0.196``, which is *free* at ``free_thresh: 0.25``; 128 is ``occ = 0.498``, unknown at
any sane thresholds.  A cell is written occupied when its probability is at least
``occupied_thresh``, free when at most ``free_thresh``, unknown otherwise (and where the map
knows nothing: log-odds exactly 0).

Reading (:func:`read_nav2`) applies map_server's rules to any image OpenCV decodes (PGM, PNG,
BMP, ...), for the modes ``trinary``, ``scale`` and ``raw``, with ``negate`` and alpha as
map_server does, and returns nav_msgs occupancy (0..100, -1) in grid order with its geometry.

Costmap filter masks (:func:`export_mask`): the keepout mask in ``trinary`` mode (100 kept
out, 0 free, -1 unknown), the speed mask in ``scale`` mode with ``occupied_thresh: 1.0`` and
``free_thresh: 0.0``, so map_server reads each pixel back as its limit in percent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import yaml

from sogm_service.adapters.ros2.convert import ValueKind, occupancy_from_values
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.wire.messages import IsmMessage, PoseModel

OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.25
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
PIXEL_UNKNOWN = 128
MAX_IMAGE_CELLS = 16384 * 16384


class Nav2MapError(ValueError):
    """A nav2 map file that cannot be read: ``code`` and a sentence."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.parameter: str | None = None


@dataclass(frozen=True)
class Nav2Map:
    """A map read from a nav2 YAML: occupancy in grid order (row 0 = smallest y)."""

    occupancy: npt.NDArray[np.int8]
    geometry: GridGeometry
    image: Path
    mode: str

    def ism(self, *, frame: str = "map", stamp: float = 0.0, layer: str | None = None,
            robot: str | None = None) -> IsmMessage:
        """The map as an ``occupancy_i8`` ISM (a prior for ``import nav2``)."""
        g = self.geometry
        return IsmMessage(layer=layer, robot=robot, frame=frame, stamp=float(stamp),
                          resolution=g.resolution,
                          origin=PoseModel(x=g.origin.x, y=g.origin.y, yaw=g.origin.yaw),
                          width=g.width, height=g.height, encoding="occupancy_i8",
                          data=np.ascontiguousarray(self.occupancy).tobytes())

    def ism_chunks(self, max_side: int = 1024, **kw: Any) -> list[IsmMessage]:
        """The map as ISMs of at most ``max_side`` x ``max_side`` cells (for maps beyond the
        server's ``max_ism_cells`` / ``max_ism_tiles``); blocks with no known cell are left
        out.  ``kw`` as :meth:`ism`."""
        if max_side < 1:
            raise ValueError("max_side must be >= 1")
        out = []
        h, w = self.occupancy.shape
        for v0 in range(0, h, max_side):
            for u0 in range(0, w, max_side):
                block = self.occupancy[v0:v0 + max_side, u0:u0 + max_side]
                if not (block >= 0).any():
                    continue
                geom = self.geometry.subgrid(u0, v0, block.shape[1], block.shape[0])
                out.append(Nav2Map(np.ascontiguousarray(block), geom, self.image,
                                   self.mode).ism(**kw))
        return out


def trinary_pixels(values: npt.ArrayLike, kind: ValueKind, *,
                   occupied_thresh: float = OCCUPIED_THRESH,
                   free_thresh: float = FREE_THRESH) -> npt.NDArray[np.uint8]:
    """Map values -> trinary pixels in grid order (no flip)."""
    occ = occupancy_from_values(values, kind).astype(np.int16)
    px = np.full(occ.shape, PIXEL_UNKNOWN, dtype=np.uint8)
    known = occ >= 0
    px[known & (occ <= round(free_thresh * 100))] = PIXEL_FREE
    px[known & (occ >= round(occupied_thresh * 100))] = PIXEL_OCCUPIED
    return px


@dataclass(frozen=True)
class TrinaryCounts:
    """How many cells of a trinary map are free, occupied and unknown."""

    free: int
    occupied: int
    unknown: int

    def __str__(self) -> str:
        return f"{self.free} free, {self.occupied} occupied, {self.unknown} unknown"


def trinary_counts(pixels: npt.NDArray[np.uint8]) -> TrinaryCounts:
    """The cells of :func:`trinary_pixels` by kind: what nav2 will plan through, avoid and
    treat as unexplored."""
    px = np.asarray(pixels)
    return TrinaryCounts(int(np.count_nonzero(px == PIXEL_FREE)),
                         int(np.count_nonzero(px == PIXEL_OCCUPIED)),
                         int(np.count_nonzero(px == PIXEL_UNKNOWN)))


def _yaml_float(v: float) -> str:
    return repr(float(v))


def export_nav2(directory: str | Path, values: npt.ArrayLike, geometry: GridGeometry, *,
                kind: ValueKind = "logodds", name: str = "map",
                occupied_thresh: float = OCCUPIED_THRESH,
                free_thresh: float = FREE_THRESH) -> tuple[Path, Path]:
    """Write ``<name>.yaml`` and ``<name>.pgm`` into ``directory``; returns both paths.

    ``values`` is the ``(height, width)`` window of ``geometry`` (probabilities, float
    log-odds in nats, or the map's fixed-point log-odds, after ``kind``).
    """
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:
        raise ValueError("need 0 <= free_thresh < occupied_thresh <= 1")
    arr = np.asarray(values)
    if arr.shape != geometry.shape:
        raise ValueError(f"values of shape {arr.shape}, geometry {geometry.shape}")
    px = trinary_pixels(arr, kind, occupied_thresh=occupied_thresh, free_thresh=free_thresh)
    return _write_map(Path(directory), name, px, geometry, mode="trinary",
                      occupied_thresh=occupied_thresh, free_thresh=free_thresh)


def _number(doc: dict[str, Any], key: str, default: float | None = None) -> float:
    v = doc.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise Nav2MapError("invalid_value", f"{key}: expected a finite number, got {v!r}")
    return float(v)


def read_nav2(map_yaml: str | Path, *, max_cells: int = MAX_IMAGE_CELLS) -> Nav2Map:
    """Read a nav2 map YAML and its image with map_server's rules."""
    path = Path(map_yaml)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise Nav2MapError("not_found", f"cannot read {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise Nav2MapError("invalid_value", f"{path} is not valid YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise Nav2MapError("invalid_value", f"{path} is not a YAML mapping")
    for key in ("image", "resolution", "origin"):
        if key not in doc:
            raise Nav2MapError("missing_field", f"{path}: no {key!r}")
    res = _number(doc, "resolution")
    if res <= 0:
        raise Nav2MapError("non_positive_resolution", f"resolution must be > 0, got {res}")
    origin = doc["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise Nav2MapError("invalid_value", "origin must be [x, y, yaw]")
    ox, oy, oyaw = (_number({"origin": v}, "origin") for v in origin)
    occ_t = _number(doc, "occupied_thresh", OCCUPIED_THRESH)
    free_t = _number(doc, "free_thresh", FREE_THRESH)
    negate = bool(int(_number(doc, "negate", 0)))
    mode = str(doc.get("mode", "trinary")).lower()
    if mode not in ("trinary", "scale", "raw"):
        raise Nav2MapError("invalid_value", f"mode {mode!r} is not trinary, scale or raw")
    image = Path(str(doc["image"]))
    if not image.is_absolute():
        image = path.parent / image
    img = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise Nav2MapError("not_found", f"cannot read the image {image}")
    if img.shape[0] * img.shape[1] > max_cells:
        raise Nav2MapError("too_large", f"{img.shape[1]}x{img.shape[0]} pixels exceed "
                                        f"{max_cells}")
    occ = _occupancy(img, mode, negate, occ_t, free_t)
    grid = np.ascontiguousarray(np.flipud(occ))  # grid row 0 = the image's bottom row
    h, w = grid.shape
    return Nav2Map(grid, GridGeometry(res, w, h, Pose2D(ox, oy, oyaw)), image, mode)


def _occupancy(img: npt.NDArray[Any], mode: str, negate: bool, occ_t: float,
               free_t: float) -> npt.NDArray[np.int8]:
    """map_server's pixel rules, image order.  OpenCV gives BGR(A); the mean is the same."""
    scale = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else 1.0
    a = img.astype(np.float64) / scale
    alpha: npt.NDArray[np.float64] | None = None
    if a.ndim == 2:
        colour = a
    elif a.shape[2] in (2, 4):  # grey + alpha, BGRA
        alpha = a[..., -1]
        colour = a[..., :-1].mean(axis=2)
    else:
        colour = a.mean(axis=2)
    channels = 1 if a.ndim == 2 else a.shape[2] - (1 if alpha is not None else 0)
    if mode == "trinary" and alpha is not None:  # map_server averages in 1 - alpha
        shade = (colour * channels + (1.0 - alpha)) / (channels + 1)
    else:
        shade = colour
    if mode == "raw":
        value = np.rint(shade * 255.0)
        return np.where(value > 100, -1, value).astype(np.int8)  # raw: the value, -1 > 100
    occ = shade if negate else 1.0 - shade
    out = np.full(occ.shape, -1, dtype=np.int8)
    if mode == "trinary":
        out[occ > occ_t] = 100
        out[occ < free_t] = 0
        return out
    transparent = (alpha < 1.0) if alpha is not None else np.zeros(occ.shape, bool)
    ratio = np.rint((occ - free_t) / (occ_t - free_t) * 100.0)
    out[:] = np.clip(ratio, 0, 100).astype(np.int8)
    out[occ > occ_t] = 100
    out[occ < free_t] = 0
    out[transparent] = -1
    return out


# -- nav2 costmap filter masks ---------------------------------------------------------------
MASK_MODES = {"keepout": "trinary", "speed": "scale"}
"""The map_server mode each filter mask is written in (nav2's filter tutorials use these)."""


def mask_pixels(cells: npt.ArrayLike, mode: str) -> npt.NDArray[np.uint8]:
    """Mask cells (0..100, -1) -> pixels in grid order that map_server reads back as them.

    ``trinary`` (at thresholds 0.65 / 0.25): 100 -> 0, 0 -> 254, -1 -> 128; only those three
    values.  ``scale`` (thresholds 1.0 / 0.0, so a cell is ``rint(occ * 100)`` with
    ``occ = 1 - pixel / 255``): ``v -> round(255 * (1 - v / 100))``; no -1 (an opaque image has
    no unknown in scale mode).
    """
    v = np.asarray(cells, dtype=np.int16)
    if mode == "trinary":
        if not np.isin(v, (-1, 0, 100)).all():
            raise ValueError("a trinary mask holds only 100, 0 and -1")
        px = np.full(v.shape, PIXEL_UNKNOWN, np.uint8)
        px[v == 100] = PIXEL_OCCUPIED
        px[v == 0] = PIXEL_FREE
        return px
    if mode == "scale":
        if v.size and (v.min() < 0 or v.max() > 100):
            raise ValueError("a scale mask holds values 0..100")
        return np.rint(255.0 * (1.0 - v / 100.0)).astype(np.uint8)
    raise ValueError(f"mode {mode!r} is not trinary or scale")


def export_mask(directory: str | Path, cells: npt.ArrayLike, geometry: GridGeometry, *,
                mode: str, name: str) -> tuple[Path, Path]:
    """Write a costmap filter mask as ``<name>.yaml`` + ``<name>.pgm`` for nav2's map_server
    (``mode`` ``trinary`` for keepout, ``scale`` for speed: :func:`mask_pixels`)."""
    arr = np.asarray(cells)
    if arr.shape != geometry.shape:
        raise ValueError(f"cells of shape {arr.shape}, geometry {geometry.shape}")
    occ_t, free_t = (OCCUPIED_THRESH, FREE_THRESH) if mode == "trinary" else (1.0, 0.0)
    return _write_map(Path(directory), name, mask_pixels(arr, mode), geometry, mode=mode,
                      occupied_thresh=occ_t, free_thresh=free_t)


def _write_map(out: Path, name: str, px: npt.NDArray[np.uint8], geometry: GridGeometry, *,
               mode: str, occupied_thresh: float, free_thresh: float) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    pgm, yml = out / f"{name}.pgm", out / f"{name}.yaml"
    image = np.ascontiguousarray(np.flipud(px))  # image top row = largest y
    header = f"P5\n# sogm-service export\n{geometry.width} {geometry.height}\n255\n"
    tmp = pgm.with_suffix(".pgm.tmp")
    tmp.write_bytes(header.encode("ascii") + image.tobytes())
    tmp.replace(pgm)
    o = geometry.origin
    text = (f"image: {pgm.name}\n"
            f"mode: {mode}\n"
            f"resolution: {_yaml_float(geometry.resolution)}\n"
            f"origin: [{_yaml_float(o.x)}, {_yaml_float(o.y)}, {_yaml_float(o.yaw)}]\n"
            f"negate: 0\n"
            f"occupied_thresh: {_yaml_float(occupied_thresh)}\n"
            f"free_thresh: {_yaml_float(free_thresh)}\n")
    tmp = yml.with_suffix(".yaml.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(yml)
    return yml, pgm
