"""The messages on the wire, as pydantic models (architecture, section 5:
docs/architecture.md#5-the-wire): what robots send (ISMs, poses), the server's reports (tile
events, match and rejection reports, acks, error replies) and the types they share.  The queries'
requests and replies are in :mod:`sogm_service.wire.queries`.

Payloads are msgpack maps of these models' fields (see :mod:`sogm_service.wire.codec`).  Arrays
travel as :class:`WireArray`: raw little-endian bytes plus dtype and shape.  ISMs carry their
cells as raw bytes whose layout is fixed by ``width``, ``height`` and ``encoding`` so that a
robot in any language can produce one without a numpy-like array type.

Validation happens here, once, at the edge: a model that validates is safe for the core.  Each
rejection carries a machine-readable ``code`` (the pydantic error type; our own validators raise
:class:`pydantic_core.PydanticCustomError` with the codes listed in
:data:`~sogm_service.wire.errors.DECODE_CODES`).
"""

from __future__ import annotations

import math
from typing import Annotated, ClassVar, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationInfo, field_validator
from pydantic import model_validator as _model_validator
from pydantic_core import PydanticCustomError

from sogm_service.core.logodds import ENCODING_DTYPES, Encoding
from sogm_service.wire import compression as zstd
from sogm_service.wire.compression import Compression
from sogm_service.wire.errors import DecodeError
from sogm_service.wire.limits import MAX_ISM_CELLS

SCHEMA_VERSION = 3
"""Version of the wire schemas (``x-sogm-schema-version`` in ``schemas/*.json``).  Version 2
added the ``prob_u8_v2`` encoding and NaN as "unknown" in ``prob_f32``; version 3 added
``compression`` to ISMs (zstd ``data``).  Every older message is a valid message of the newer
versions with the same meaning."""

IsmEncoding = Literal["occupancy_i8", "prob_u8", "prob_f32", "prob_u8_v2"]
OutputEncoding = Literal["prob_u8", "prob_f32", "logodds_i16", "occupancy_i8", "prob_u8_v2"]

ENCODING_DESCRIPTION = (
    "Cell encoding. occupancy_i8: nav_msgs/OccupancyGrid, 0..100 percent, -1 = unknown. "
    "prob_u8: p = v / 255 (the original 8-bit encoding, unchanged; it has no exact unknown: "
    "128 is p = 0.502). prob_u8_v2 (added in schema version 2): 0..254 is p = v / 254 "
    "(127 is exactly 0.5), 255 = unknown; both 127 and 255 leave a cell untouched. "
    "prob_f32: p in [0, 1], NaN = unknown (no update; rejected before schema version 2). "
    "logodds_i16 (replies only): log-odds in units of 1/1000 nat.")
COMPRESSION_DESCRIPTION = (
    "Compression of data (added in schema version 3). Absent or null: raw cells. zstd: one zstd "
    "frame that declares its decompressed size, which must be exactly width x height x the "
    "encoding's cell size (refused as data_length otherwise, bad_compression when it is not one "
    "such frame); the server prices the ISM from its header before decompressing.")
FusionMethod = Literal["bayes", "max"]

StrictInt = Annotated[int, Strict()]
StrictStr = Annotated[str, Strict()]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
# Robots' messages are typed strictly: true is not 1.0 m and "0.05" is not a number.
WireFloat = Annotated[float, Strict(), Field(allow_inf_nan=False)]
StrictBytes = Annotated[bytes, Strict()]


class WireModel(BaseModel):
    """Base of every wire message: immutable, unknown fields ignored (forward compatible)."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)
    schema_name: ClassVar[str] = ""


class WireArray(WireModel):
    """An n-d array as raw little-endian bytes, its dtype string and shape."""

    dtype: Literal["uint8", "int8", "int16", "int32", "float32", "float64"]
    shape: list[StrictInt]
    data: bytes

    @_model_validator(mode="after")
    def _length_matches(self) -> WireArray:
        if any(s < 0 for s in self.shape):
            raise PydanticCustomError("invalid_value", "array shape has a negative size")
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != expected:
            raise PydanticCustomError(
                "data_length", "array data has {got} bytes, shape and dtype need {expected}",
                {"got": len(self.data), "expected": expected})
        return self

    @staticmethod
    def from_array(a: npt.NDArray) -> WireArray:
        le = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
        return WireArray(dtype=str(a.dtype.name), shape=list(a.shape), data=le.tobytes())

    def array(self) -> npt.NDArray:
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype).newbyteorder("<")) \
            .astype(self.dtype).reshape(self.shape)


class PoseModel(WireModel):
    """A planar pose (m, rad) in the message's frame."""

    x: WireFloat = 0.0
    y: WireFloat = 0.0
    yaw: WireFloat = 0.0


class GeodeticFix(WireModel):
    """WGS-84 latitude/longitude (deg) and altitude (m), as sensor_msgs/NavSatFix."""

    latitude: Annotated[float, Field(ge=-90, le=90, allow_inf_nan=False)]
    longitude: Annotated[float, Field(ge=-180, le=180, allow_inf_nan=False)]
    altitude: FiniteFloat = 0.0


class IsmHeader(WireModel):
    """The header of an ISM: every field of :class:`IsmMessage` but its cells.

    What every step that reads only the header takes (the footprint, the frame, the geometry,
    the layer name).  The fields and their checks are the message's own (it extends this).
    """

    layer: StrictStr | None = None
    frame: StrictStr = "map"
    stamp: WireFloat = 0.0
    robot: StrictStr | None = None
    resolution: Annotated[float, Strict()]
    origin: PoseModel = PoseModel()
    width: StrictInt
    height: StrictInt
    encoding: Annotated[IsmEncoding, Field(description=ENCODING_DESCRIPTION)]

    @field_validator("resolution")
    @classmethod
    def _positive_resolution(cls, v: float) -> float:
        if not math.isfinite(v):
            raise PydanticCustomError("non_finite", "resolution is not finite")
        if v <= 0:
            raise PydanticCustomError("non_positive_resolution",
                                      "resolution must be > 0, got {v}", {"v": v})
        return v

    @field_validator("width", "height")
    @classmethod
    def _positive_size(cls, v: int) -> int:
        if v <= 0:
            raise PydanticCustomError("invalid_value", "grid sizes must be > 0, got {v}",
                                      {"v": v})
        return v

    @_model_validator(mode="after")
    def _check_cells(self, info: ValidationInfo) -> IsmHeader:
        limits = info.context or {}
        max_cells = int(limits.get("max_cells", MAX_ISM_CELLS))
        cells = self.width * self.height
        if cells > max_cells:
            raise PydanticCustomError("too_large", "{cells} cells exceed the limit of {limit}",
                                      {"cells": cells, "limit": max_cells})
        return self


class IsmMessage(IsmHeader):
    """An inverse sensor model: one semantic class observed as a grid in its own pose.

    ``layer`` may be omitted: the server then names the layer after the key's remainder
    (``ism/robot1/laser/obstacle`` -> ``robot1/laser/obstacle``).
    """

    schema_name: ClassVar[str] = "ism"
    data: StrictBytes
    compression: Annotated[Compression | None, Field(description=COMPRESSION_DESCRIPTION)] = None

    @_model_validator(mode="after")
    def _check_data(self, info: ValidationInfo) -> IsmMessage:
        """The cells: their length, or the zstd frame's declared size and content, and their
        values.  With ``framing_only`` in the context a zstd frame is checked from its header
        alone and kept as sent (``compression`` stays set, the cells are not readable): what a
        cluster member that owns none of the ISM's tiles checks, leaving the decompression to
        the owners.  Raw cells are checked whole either way (it costs little)."""
        cells = self.width * self.height  # within the limit: the header's check ran first
        itemsize = ENCODING_DTYPES[Encoding(self.encoding)].itemsize
        if self.compression is not None:
            if (info.context or {}).get("framing_only"):
                self._check_frame(cells * itemsize)
                return self
            self._decompress(cells * itemsize)
        if len(self.data) != cells * itemsize:
            raise PydanticCustomError(
                "data_length",
                "data has {got} bytes; {w}x{h} cells of {enc} need {expected}",
                {"got": len(self.data), "w": self.width, "h": self.height,
                 "enc": self.encoding, "expected": cells * itemsize})
        _check_cell_values(self.array(), self.encoding)
        return self

    def _check_frame(self, expected: int) -> None:
        try:
            zstd.check_declared_size(self.data, expected)
        except DecodeError as exc:
            raise PydanticCustomError(exc.code, exc.message) from None

    def _decompress(self, expected: int) -> None:
        """Replace zstd ``data`` by the raw cells: only a frame that declares exactly the size
        the header implies is decompressed (priced before any work); the message then reads as
        the uncompressed ISM it stands for."""
        try:
            raw = zstd.decompress(self.data, expected)
        except DecodeError as exc:
            raise PydanticCustomError(exc.code, exc.message) from None
        object.__setattr__(self, "data", raw)  # frozen model: the validated, expanded cells
        object.__setattr__(self, "compression", None)

    def compressed(self) -> IsmMessage:
        """The same ISM with zstd ``data`` (what robots send over thin links)."""
        if self.compression is not None:
            return self
        return self.model_copy(update={"data": zstd.compress(self.data),
                                       "compression": zstd.ZSTD})

    def array(self) -> npt.NDArray:
        """The cells as a ``(height, width)`` array of the encoding's dtype (read-only view)."""
        dtype = ENCODING_DTYPES[Encoding(self.encoding)].newbyteorder("<")
        return np.frombuffer(self.data, dtype=dtype).reshape(self.height, self.width)


def _check_cell_values(a: npt.NDArray, encoding: str) -> None:
    if encoding == "prob_f32":
        # NaN is "unknown" (no update); infinities are refused.  NaN compares False, so the
        # range test below passes it and catches everything else outside [0, 1].
        if np.isinf(a).any():
            raise PydanticCustomError("non_finite", "prob_f32 data holds an infinity")
        if a.size and bool(((a < 0.0) | (a > 1.0)).any()):
            raise PydanticCustomError("out_of_range", "prob_f32 data outside [0, 1]")
    elif encoding == "occupancy_i8":
        bad = (a < -1) | (a > 100)
        if bad.any():
            raise PydanticCustomError(
                "out_of_range", "occupancy_i8 data holds {n} values outside 0..100 and -1",
                {"n": int(bad.sum())})


class PoseMessage(WireModel):
    """A robot's pose, as the tile manager follows it."""

    schema_name: ClassVar[str] = "pose"
    robot: StrictStr | None = None
    frame: StrictStr = "map"
    stamp: WireFloat = 0.0
    x: WireFloat
    y: WireFloat
    yaw: WireFloat = 0.0
    fix: GeodeticFix | None = None


class TileEvent(WireModel):
    """A robot entered a new tile (the paper's Pose/NavSat/String tuple)."""

    schema_name: ClassVar[str] = "tile_event"
    map: str
    robot: str
    i: int
    j: int
    name: str
    origin: PoseModel
    datum: GeodeticFix | None = None
    stamp: float


class MatchReport(WireModel):
    """The outcome of scan matching one ISM (paper section III-C.2), for localisation stacks.

    ``correction`` takes the claimed ISM origin to the matched one, in the map frame; it is
    published whether or not the server fused the corrected ISM (``mode``).
    """

    schema_name: ClassVar[str] = "match_report"
    map: str
    key: str
    layer: str
    robot: str | None
    stamp: float
    mode: Literal["correct", "report"]
    accepted: bool
    reason: str
    claimed: PoseModel
    corrected: PoseModel | None
    dx_m: float | None
    dy_m: float | None
    dyaw_rad: float | None
    inliers: int
    score_before: float | None
    score_after: float | None
    elapsed_ms: float


class RobotTilesReply(WireModel):
    """Each robot's current tile (its last tile-switch event): what a late joiner needs."""

    schema_name: ClassVar[str] = "robot_tiles"
    map: str
    robots: list[TileEvent]


class ErrorReply(WireModel):
    """What a failed query gets back (with ``reply_err``)."""

    schema_name: ClassVar[str] = "error"
    code: str
    message: str
    parameter: str | None = None
    retry_after_s: float | None = None  # with ``busy``: when to ask again (seconds)


class RejectionReport(WireModel):
    """An ISM the server rejected, published on ``<prefix>/<map>/rejections/<robot>`` (the
    robot chunk of the ISM's key) so the publisher hears why."""

    schema_name: ClassVar[str] = "rejection"
    key: str
    code: str
    message: str
    stamp: float
    id: str | None = None  # the ISM's id when it was published with one (the attachment)


class IsmAck(WireModel):
    """What became of an ISM published with an id (queryable ``<prefix>/<map>/ack?id=...``):
    ``queued`` (received, not yet fused), ``fused`` (in the map: a query sees it),
    ``rejected`` (``code``, ``message``) or ``unknown`` (never received, or too long ago)."""

    schema_name: ClassVar[str] = "ism_ack"
    id: str
    status: Literal["queued", "fused", "rejected", "unknown"]
    key: str = ""
    code: str | None = None
    message: str = ""
    stamp: float = 0.0


class DropLayersReply(WireModel):
    """What a server removed for a get on ``<prefix>/<map>/drop/<pattern>``: the layers
    matching ``pattern`` (gone from the map and its store), the tiles that lost a plane
    (rewritten) and those left without any layer (removed), and whether the store already
    holds the result (``stored``; a server without a store has nothing to rewrite)."""

    schema_name: ClassVar[str] = "drop_layers_reply"
    map: str
    server_id: str
    pattern: str
    layers: list[str]
    tiles_rewritten: int
    tiles_removed: int
    stored: bool
