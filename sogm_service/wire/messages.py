"""Every message on the wire, as pydantic models (architecture, section 5:
docs/architecture.md#5-the-wire).

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
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationInfo, field_validator
from pydantic import model_validator as _model_validator
from pydantic_core import PydanticCustomError

from sogm_service.core.logodds import ENCODING_DTYPES, Encoding
from sogm_service.core.resample import Interp
from sogm_service.core.sevds.segment import BOUNDS as _SEVDS_BOUNDS
from sogm_service.core.sevds.segment import Criterion, SevdsParams
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



_SEVDS = SevdsParams()  # the defaults of a supercells query


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


class IsmMessage(WireModel):
    """An inverse sensor model: one semantic class observed as a grid in its own pose.

    ``layer`` may be omitted: the server then names the layer after the key's remainder
    (``ism/robot1/laser/obstacle`` -> ``robot1/laser/obstacle``).
    """

    schema_name: ClassVar[str] = "ism"
    layer: StrictStr | None = None
    frame: StrictStr = "map"
    stamp: WireFloat = 0.0
    robot: StrictStr | None = None
    resolution: Annotated[float, Strict()]
    origin: PoseModel = PoseModel()
    width: StrictInt
    height: StrictInt
    encoding: Annotated[IsmEncoding, Field(description=ENCODING_DESCRIPTION)]
    data: StrictBytes
    compression: Annotated[Compression | None, Field(description=COMPRESSION_DESCRIPTION)] = None

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
    def _check_data(self, info: ValidationInfo) -> IsmMessage:
        limits = info.context or {}
        max_cells = int(limits.get("max_cells", MAX_ISM_CELLS))
        cells = self.width * self.height
        if cells > max_cells:
            raise PydanticCustomError("too_large", "{cells} cells exceed the limit of {limit}",
                                      {"cells": cells, "limit": max_cells})
        itemsize = ENCODING_DTYPES[Encoding(self.encoding)].itemsize
        if self.compression is not None:
            self._decompress(cells * itemsize)
        if len(self.data) != cells * itemsize:
            raise PydanticCustomError(
                "data_length",
                "data has {got} bytes; {w}x{h} cells of {enc} need {expected}",
                {"got": len(self.data), "w": self.width, "h": self.height,
                 "enc": self.encoding, "expected": cells * itemsize})
        _check_cell_values(self.array(), self.encoding)
        return self

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


class WindowRequest(BaseModel):
    """A window of the map: centre pose, size (m), resolution (m), layers.

    Requests come as selector parameters (strings) or a msgpack body, so they are validated in
    lax mode; unknown parameters are refused so a typo never silently does something else.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    schema_name: ClassVar[str] = ""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    width: Annotated[float, Field(gt=0)] = 10.0
    height: Annotated[float, Field(gt=0)] = 10.0
    resolution: Annotated[float, Field(gt=0)] | None = None
    layers: list[str] | None = None
    interp: Interp = "biodds"
    encoding: OutputEncoding = "prob_u8"
    compression: Annotated[Compression | None, Field(description=(
        "Compress the reply: zstd sends the msgpack reply as one zstd frame, declared as the "
        "Zenoh encoding application/msgpack;zstd (error replies are never compressed)."))] = None

    @field_validator("layers", mode="before")
    @classmethod
    def _split_layers(cls, v: Any) -> Any:
        if isinstance(v, str):
            return [s for s in v.split(",") if s]
        return v


class SubmapRequest(WindowRequest):
    schema_name: ClassVar[str] = "submap_request"


class FusedRequest(WindowRequest):
    schema_name: ClassVar[str] = "fused_request"
    method: FusionMethod = "bayes"


class SupercellRequest(WindowRequest):
    """Window + SEVDS parameters (paper section III-D.2)."""

    schema_name: ClassVar[str] = "supercell_request"
    block_size: Annotated[int, Field(ge=_SEVDS_BOUNDS["block_size"][0],
                                     le=_SEVDS_BOUNDS["block_size"][1])] = _SEVDS.block_size
    levels: Annotated[int, Field(ge=_SEVDS_BOUNDS["levels"][0],
                                 le=_SEVDS_BOUNDS["levels"][1])] = _SEVDS.levels
    bins: Annotated[int, Field(ge=_SEVDS_BOUNDS["bins"][0],
                               le=_SEVDS_BOUNDS["bins"][1])] = _SEVDS.bins
    iterations: Annotated[int, Field(ge=_SEVDS_BOUNDS["iterations"][0],
                                     le=_SEVDS_BOUNDS["iterations"][1])] = _SEVDS.iterations
    gamma: Annotated[float, Field(ge=0)] = _SEVDS.gamma  # tuned on the evaluation scenes
    criterion: Criterion = _SEVDS.criterion
    labels: bool = False


class WindowReply(WireModel):
    """Where a reply's window lies: cells of ``resolution`` m from the corner ``origin``."""

    map: str
    frame: str
    stamp: float
    resolution: float
    origin: PoseModel
    width: int
    height: int
    layers: list[str]


class GridReply(WindowReply):
    """A sub-map: ``(N, H, W)`` cells of the named layers."""

    schema_name: ClassVar[str] = "submap_reply"
    encoding: OutputEncoding
    interp: Interp
    data: WireArray


class FusedReply(WindowReply):
    """One layer fused from several by Eq. 6 (``bayes``: P_B, ``max``: P_M)."""

    schema_name: ClassVar[str] = "fused_reply"
    method: FusionMethod
    encoding: OutputEncoding
    interp: Interp
    data: WireArray


class SupercellNode(WireModel):
    """One supercell of the topometric graph: the paper's triple (T_c, L_c, P_c), Eq. 11."""

    id: int
    x: float
    y: float
    area_cells: int
    area_m2: float
    neighbors: list[int]
    logodds_sum: list[float]
    mean_probability: list[float]


class SupercellReply(WindowReply):
    """The topometric graph of a window (paper Fig. 6); the label image on request."""

    schema_name: ClassVar[str] = "supercell_reply"
    nodes: list[SupercellNode]
    labels: WireArray | None = None


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


class InfoReply(WireModel):
    schema_name: ClassVar[str] = "info"
    map: str
    frame: str
    server_id: str
    resolution: float
    tile_size: int
    eps0: float
    logodds_scale: float
    layers: list[str]
    tiles: list[tuple[int, int]]
    bounds: tuple[float, float, float, float] | None
    datum: GeodeticFix | None = None


class StatsReply(WireModel):
    schema_name: ClassVar[str] = "stats"
    map: str
    server_id: str
    uptime_s: float
    counters: dict[str, int]
    rejected: dict[str, int]
    queue_depth: int
    isms_per_s: float
    latency_ms: dict[str, dict[str, float]]
    extra: dict[str, Any] = {}


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


TileVersion = Annotated[int, Field(ge=0, lt=1 << 63)]


class TilesChangedRequest(BaseModel):
    """``tiles/changed``: the tiles of a region whose version differs from the one held.

    The region is a box of the map frame (``x``, ``y`` its centre, ``width``, ``height`` in m)
    or tile index bounds (``i0``..``i1``, ``j0``..``j1``, inclusive); ``held`` the versions the
    client holds, ``{"i,j": version}`` or ``[[i, j, version], ...]``.  Lax (selector strings)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    schema_name: ClassVar[str] = "tiles_changed_request"

    x: float = 0.0
    y: float = 0.0
    width: Annotated[float, Field(gt=0)] | None = None
    height: Annotated[float, Field(gt=0)] | None = None
    i0: int | None = None
    j0: int | None = None
    i1: int | None = None
    j1: int | None = None
    held: dict[str, TileVersion] | list[tuple[int, int, TileVersion]] = {}


SCHEMA_MODELS: tuple[type[BaseModel], ...] = (
    IsmMessage, PoseMessage, SubmapRequest, FusedRequest, SupercellRequest, GridReply,
    FusedReply, SupercellReply, TileEvent, RobotTilesReply, MatchReport, InfoReply, StatsReply,
    ErrorReply, RejectionReport, IsmAck, TilesChangedRequest,
)
