r"""The queries' wire models: the window requests (sub-map, fused, supercells, tiles changed)
and their replies (grids, graphs, info, stats).

Requests come as selector parameters (strings, :func:`selector_params`) or a msgpack body
(:func:`unpack_body`), validated by :func:`sogm_service.service.server.queries.parse_request`
and typed strictly, as ISMs are: a selector's strings are parsed as the field's type, a body's
values must already be of it (``true`` is not a number, ``"10"`` is not a width), a parameter
given twice is refused, and so is an unknown one.  Replies are
:class:`~sogm_service.wire.messages.WireModel`\ s like every message the server sends.  What
robots send (ISMs, poses) and the server's reports are in :mod:`sogm_service.wire.messages`.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated, Any, ClassVar

import msgpack
from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator

from sogm_service.core.resample import Interp
from sogm_service.core.sevds.segment import BOUNDS as _SEVDS_BOUNDS
from sogm_service.core.sevds.segment import Criterion, SevdsParams
from sogm_service.wire.compression import Compression
from sogm_service.wire.errors import QueryError
from sogm_service.wire.limits import (
    MAX_LAYER_NAME,
    MAX_LAYERS,
    MAX_MSGPACK_STR,
    MAX_PAYLOAD_BYTES,
)
from sogm_service.wire.messages import (
    FusionMethod,
    GeodeticFix,
    OutputEncoding,
    PoseModel,
    StrictInt,
    StrictStr,
    WireArray,
    WireFloat,
    WireModel,
)

_SEVDS = SevdsParams()  # the defaults of a supercells query

LAYER_ENTRY_PATTERN = rf"^[A-Za-z0-9_\-./*?\[\]!]{{1,{MAX_LAYER_NAME}}}$"
"""An entry of ``layers``: a layer's name, or a glob pattern over names (``*``, ``?``,
``[...]``, ``[!...]``) naming a class (:mod:`sogm_service.core.classes`)."""

LayerEntry = Annotated[StrictStr, Field(pattern=LAYER_ENTRY_PATTERN)]
StrictBool = Annotated[bool, Strict()]
Positive = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]


class WindowRequest(BaseModel):
    """A window of the map: centre pose, size (m), resolution (m), layers.

    Requests come as selector parameters (strings) or a msgpack body, typed strictly (see the
    module); unknown parameters are refused so a typo never silently does something else.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    schema_name: ClassVar[str] = ""

    x: WireFloat = 0.0
    y: WireFloat = 0.0
    yaw: WireFloat = 0.0
    width: Positive = 10.0
    height: Positive = 10.0
    resolution: Positive | None = None
    layers: Annotated[list[LayerEntry] | None, Field(max_length=MAX_LAYERS, description=(
        "Layers of the reply (default all), comma-separated in a selector: each a layer's "
        "name, or a glob pattern (*, ?, [...], '*' crossing '/') naming a class, the matching "
        "layers fused by the Bayesian rule into one plane named by the pattern."))] = None
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
    block_size: Annotated[StrictInt, Field(ge=_SEVDS_BOUNDS["block_size"][0],
                                     le=_SEVDS_BOUNDS["block_size"][1])] = _SEVDS.block_size
    levels: Annotated[StrictInt, Field(ge=_SEVDS_BOUNDS["levels"][0],
                                 le=_SEVDS_BOUNDS["levels"][1])] = _SEVDS.levels
    bins: Annotated[StrictInt, Field(ge=_SEVDS_BOUNDS["bins"][0],
                               le=_SEVDS_BOUNDS["bins"][1])] = _SEVDS.bins
    iterations: Annotated[StrictInt, Field(ge=_SEVDS_BOUNDS["iterations"][0],
                                     le=_SEVDS_BOUNDS["iterations"][1])] = _SEVDS.iterations
    gamma: Annotated[WireFloat, Field(ge=0)] = _SEVDS.gamma  # tuned on the room maps
    criterion: Criterion = _SEVDS.criterion
    labels: StrictBool = False


class WindowReply(WireModel):
    """Where a reply's window lies: cells of ``resolution`` m from the corner ``origin``.

    ``layers`` names the reply's planes: a layer's name, or the glob pattern of a class;
    ``classes`` gives each pattern's member layers (its provenance), absent without one."""

    map: str
    frame: str
    stamp: float
    resolution: float
    origin: PoseModel
    width: int
    height: int
    layers: list[str]
    classes: Annotated[dict[str, list[str]] | None, Field(description=(
        "Each glob pattern of layers and the map layers it matched, fused by the Bayesian "
        "rule into that plane (absent without a pattern)."))] = None


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


TileVersion = Annotated[StrictInt, Field(ge=0, lt=1 << 63)]


class TilesChangedRequest(BaseModel):
    """``tiles/changed``: the tiles of a region whose version differs from the one held.

    The region is a box of the map frame (``x``, ``y`` its centre, ``width``, ``height`` in m)
    or tile index bounds (``i0``..``i1``, ``j0``..``j1``, inclusive); ``held`` the versions the
    client holds, ``{"i,j": version}`` or ``[[i, j, version], ...]``.  Typed strictly, as the
    window requests."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    schema_name: ClassVar[str] = "tiles_changed_request"

    x: WireFloat = 0.0
    y: WireFloat = 0.0
    width: Positive | None = None
    height: Positive | None = None
    i0: StrictInt | None = None
    j0: StrictInt | None = None
    i1: StrictInt | None = None
    j1: StrictInt | None = None
    held: dict[str, TileVersion] | list[tuple[StrictInt, StrictInt, TileVersion]] = {}


def selector_params(pairs: Iterable[tuple[str, str]]) -> dict[str, str]:
    """A selector's parameters as a map, refusing one given twice (``width=1;width=2``) with
    ``bad_parameter``.  Parameters starting with ``_`` are Zenoh's own (``_anyke``): left out."""
    out: dict[str, str] = {}
    for key, value in pairs:
        if key.startswith("_"):
            continue
        if key in out:
            raise QueryError("bad_parameter", f"parameter {key[:40]!r} is given more than once",
                             key[:40])
        out[key] = value
    return out


def _no_repeats(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    out: dict[Any, Any] = {}
    for key, value in pairs:
        if key in out:
            raise QueryError("bad_parameter", f"key {str(key)[:40]!r} is given more than once "
                                              "in the query body", str(key)[:40])
        out[key] = value
    return out


def unpack_body(body: bytes, max_bytes: int = MAX_PAYLOAD_BYTES) -> dict[str, Any]:
    """A query's msgpack body -> its map; ``bad_parameter`` unless it is one msgpack map with
    string keys, none of them (nor any key of a map inside it) given twice."""
    if len(body) > max_bytes:
        raise QueryError("bad_parameter", f"the query body of {len(body)} bytes exceeds "
                                          f"{max_bytes}")
    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=True, max_bin_len=max_bytes,
                              max_str_len=MAX_MSGPACK_STR, object_pairs_hook=_no_repeats)
    except QueryError:
        raise
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise QueryError("bad_parameter", f"the query body is not valid msgpack: {exc}") \
            from None
    if not isinstance(obj, dict):
        raise QueryError("bad_parameter", "the query body must be a msgpack map")
    return obj
