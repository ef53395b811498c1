"""Query handling of the map server, pure: request model -> core sampling -> reply model.

Windows are priced before any work by the server's
:class:`~sogm_service.service.server.admission.Admission`: a request over a limit is refused,
never attempted.  Every refusal is a :class:`QueryError` carrying a machine-readable
code, a sentence, and the offending parameter.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, window_geometry
from sogm_service.core.map.tiles import TiledMap
from sogm_service.wire import codec
from sogm_service.wire import compression as zstd
from sogm_service.wire.codec import unpack, validate
from sogm_service.wire.compression import Compression
from sogm_service.wire.errors import DecodeError, QueryError
from sogm_service.wire.messages import PoseModel, WireArray
from sogm_service.wire.queries import (
    FusedReply,
    FusedRequest,
    GridReply,
    SubmapRequest,
    SupercellNode,
    SupercellReply,
    SupercellRequest,
    WindowRequest,
)

if TYPE_CHECKING:
    from sogm_service.service.server.admission import Admission

R = TypeVar("R", bound=BaseModel)  # a request model: a window, or the tiles changed


def parse_request(cls: type[R], params: Mapping[str, str], body: bytes | None = None) -> R:
    """Selector parameters (strings) and an optional msgpack map body -> a request model.

    Parameters given in the selector win over the body's.
    """
    merged: dict[str, Any] = {}
    try:
        if body:
            obj = unpack(body)
            if not isinstance(obj, dict):
                raise QueryError("bad_parameter", "the query body must be a msgpack map")
            merged.update(obj)
        merged.update(params)
        return validate(cls, merged)
    except DecodeError as exc:
        raise QueryError("bad_parameter", exc.message, exc.parameter) from None


def window_of(req: WindowRequest, tiled: TiledMap, n_layers: int,
              admission: Admission | None = None) -> GridGeometry:
    """The request's window geometry, priced first by ``admission`` (world, cells returned and
    read, reply bytes), so a refused window is never built.

    The server always passes its admission: it is the one place a query is priced.  In-process
    callers that build their own windows (tests, benchmarks) may pass none."""
    if admission is not None:
        admission.check_query(req, n_layers)
    res = req.resolution or tiled.lattice.resolution
    return window_geometry(req.x, req.y, req.yaw, req.width, req.height, res)


def resolve_layers(tiled: TiledMap, wanted: list[str] | None) -> list[str]:
    """The requested layers (default: all), each checked to exist."""
    if not wanted:
        return list(tiled.layers)
    unknown = [n for n in wanted if n not in tiled.layers]
    if unknown:
        raise QueryError("unknown_layer", f"unknown layer(s) {unknown}; the map has "
                                          f"{tiled.layers}", "layers")
    return list(wanted)


def _placement(tiled: TiledMap, window: GridGeometry, layers: list[str],
               stamp: float) -> dict[str, Any]:
    """The fields every window reply shares (:class:`~sogm_service.wire.messages.WindowReply`)."""
    return dict(map=tiled.name, frame=tiled.frame, stamp=stamp, resolution=window.resolution,
                origin=PoseModel(x=window.origin.x, y=window.origin.y, yaw=window.origin.yaw),
                width=window.width, height=window.height, layers=layers)


def submap(tiled: TiledMap, req: SubmapRequest, stamp: float,
           admission: Admission | None = None) -> GridReply:
    """The ``submap`` queryable: the chosen layers resampled into the requested window."""
    layers = resolve_layers(tiled, req.layers)
    window = window_of(req, tiled, len(layers), admission)
    stack = tiled.sample(window, layers, req.interp)
    data = logodds.encode_fixed(stack, req.encoding)
    return GridReply(**_placement(tiled, window, layers, stamp), encoding=req.encoding,
                     interp=req.interp, data=WireArray.from_array(data))


def fuse_layers(stack: npt.NDArray[np.int16], method: str) -> npt.NDArray[np.int32]:
    """Eq. 6 over axis 0: ``bayes`` (P_B, sum of log-odds) or ``max`` (P_M)."""
    if method == "bayes":
        return logodds.fuse_bayes(stack)
    return logodds.fuse_max(stack).astype(np.int32)


def fused(tiled: TiledMap, req: FusedRequest, stamp: float,
          admission: Admission | None = None) -> FusedReply:
    """The ``fused`` queryable: one layer pooled from the chosen ones by Eq. 6."""
    layers = resolve_layers(tiled, req.layers)
    if not layers:
        raise QueryError("unknown_layer", "the map has no layers yet", "layers")
    window = window_of(req, tiled, len(layers), admission)
    stack = tiled.sample(window, layers, req.interp)
    data = logodds.encode_fixed(fuse_layers(stack, req.method), req.encoding)
    return FusedReply(**_placement(tiled, window, layers, stamp), method=req.method,
                      encoding=req.encoding, interp=req.interp,
                      data=WireArray.from_array(data))


def supercell_input(tiled: TiledMap, req: SupercellRequest,
                    admission: Admission | None = None
                    ) -> tuple[GridGeometry, list[str], npt.NDArray[np.int16]]:
    """The window, its layers and their log-odds: all the ``supercells`` query needs from the
    map (the server holds its map lock only for this part, not for SEVDS)."""
    layers = resolve_layers(tiled, req.layers)
    if not layers:
        raise QueryError("unknown_layer", "the map has no layers yet", "layers")
    window = window_of(req, tiled, len(layers), admission)
    if min(window.width, window.height) < req.block_size:
        raise QueryError("bad_parameter", f"the window ({window.width}x{window.height} cells) "
                                          f"is smaller than one block ({req.block_size})",
                         "block_size")
    return window, layers, tiled.sample(window, layers, req.interp)


def supercells(tiled: TiledMap, req: SupercellRequest, window: GridGeometry, layers: list[str],
               stack: npt.NDArray[np.int16], stamp: float) -> SupercellReply:
    """The ``supercells`` queryable: SEVDS (Eq. 7-10) on the window, as a topometric graph.

    Each node is the paper's triple (T_c, L_c, P_c): centroid in the map frame, adjacent
    supercells, and the Eq. 11 feature vector (summed log-odds per layer, plus mean P).
    """
    from sogm_service.core.sevds.segment import (
        SevdsParams,  # numba: imported on first use, not at start
    )
    from sogm_service.core.sevds.supercells import extract_supercells

    params = SevdsParams(block_size=req.block_size, levels=req.levels, bins=req.bins,
                         iterations=req.iterations, gamma=req.gamma, criterion=req.criterion)
    graph, _ = extract_supercells(stack, window, params, tiled.eps0)
    neighbours: list[list[int]] = [[] for _ in range(graph.count)]
    for a, b in graph.edges.tolist():
        neighbours[a].append(b)
        neighbours[b].append(a)
    cell_area = window.resolution ** 2
    nodes = [SupercellNode(id=k, x=float(graph.centroids[k, 0]), y=float(graph.centroids[k, 1]),
                           area_cells=int(graph.areas[k]),
                           area_m2=float(graph.areas[k]) * cell_area, neighbors=neighbours[k],
                           logodds_sum=graph.logodds_sum[k].tolist(),
                           mean_probability=graph.mean_probability[k].tolist())
             for k in range(graph.count)]
    labels = WireArray.from_array(graph.labels) if req.labels else None
    return SupercellReply(**_placement(tiled, window, layers, stamp), nodes=nodes,
                          labels=labels)


@dataclass(frozen=True)
class Answer:
    """A reply and the compression its asker wants (``compression=zstd``)."""

    compression: Compression | None
    model: BaseModel

    @property
    def compressed(self) -> bool:
        return self.compression is not None

    def payload(self) -> bytes:
        """The msgpack reply, as one zstd frame when asked."""
        raw = codec.encode(self.model)
        return raw if self.compression is None else zstd.compress(raw)
