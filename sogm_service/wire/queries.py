r"""The queries' wire models: the window requests (sub-map, fused, supercells, tiles changed)
and their replies (grids, graphs, info, stats).

Requests come as selector parameters (strings) or a msgpack body and are validated in lax mode
with unknown parameters refused; replies are :class:`~sogm_service.wire.messages.WireModel`\ s
like every message the server sends.  What robots send (ISMs, poses) and the server's reports
are in :mod:`sogm_service.wire.messages`.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

from sogm_service.core.resample import Interp
from sogm_service.core.sevds.segment import BOUNDS as _SEVDS_BOUNDS
from sogm_service.core.sevds.segment import Criterion, SevdsParams
from sogm_service.wire.compression import Compression
from sogm_service.wire.messages import (
    FusionMethod,
    GeodeticFix,
    OutputEncoding,
    PoseModel,
    WireArray,
    WireModel,
)

_SEVDS = SevdsParams()  # the defaults of a supercells query


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
    extra: dict[str, Any] = {}  # noqa: RUF012 (pydantic copies field defaults)


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
