"""Query handling of the map server, pure: request model -> core sampling -> reply model.

Windows are priced before any work by the server's
:class:`~sogm_service.service.server.admission.Admission`: a request over a limit is refused,
never attempted.  Every refusal is a :class:`QueryError` carrying a machine-readable
code, a sentence, and the offending parameter.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ValidationError

from sogm_service.core import classes as cls_
from sogm_service.core import logodds
from sogm_service.core.classes import LayerClass
from sogm_service.core.geometry import GridGeometry, window_geometry
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server.stats import cut
from sogm_service.wire import codec
from sogm_service.wire import compression as zstd
from sogm_service.wire.codec import validation_error_to_decode_error
from sogm_service.wire.compression import Compression
from sogm_service.wire.errors import QueryError
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
    selector_params,
    unpack_body,
)

if TYPE_CHECKING:
    from sogm_service.service.server.admission import Admission

R = TypeVar("R", bound=BaseModel)  # a request model: a window, or the tiles changed
log = logging.getLogger(__name__)


class _RefusalLog:
    """One short log line per refused query parameter, at most one a second per code (the
    rest are counted, and their number said with the next line)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def __call__(self, exc: QueryError) -> QueryError:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(exc.code, -1e9) < 1.0:
                self._suppressed[exc.code] = self._suppressed.get(exc.code, 0) + 1
                return exc
            more = self._suppressed.pop(exc.code, 0)
            self._last[exc.code] = now
        log.info("refused query [%s]: %s%s", exc.code, cut(exc.message),
                 f" ({more} more of this code suppressed)" if more else "")
        return exc


_refused = _RefusalLog()


def selector(pairs: Iterable[tuple[str, str]]) -> dict[str, str]:
    """A query's selector parameters (:func:`~sogm_service.wire.queries.selector_params`:
    one given twice is ``bad_parameter``, logged)."""
    try:
        return selector_params(pairs)
    except QueryError as exc:
        raise _refused(exc) from None



def parse_request(cls: type[R], params: Mapping[str, str], body: bytes | None = None) -> R:
    """Selector parameters (strings) and an optional msgpack map body -> a request model, typed
    strictly; any problem is ``bad_parameter`` naming the parameter.

    A selector's values are strings parsed as their field's type (``width=2.5``,
    ``labels=true``); a body's values must already have it (``{"width": true}`` and
    ``{"width": "2"}`` are refused, as an ISM's would be).  A parameter is given once: twice
    in the selector or in the body is refused before this (:func:`~sogm_service.wire.queries.
    selector_params`, :func:`~sogm_service.wire.queries.unpack_body`), in both here.
    """
    try:
        return _validate(cls, params, body)
    except QueryError as exc:
        raise _refused(exc) from None


def _validate(cls: type[R], params: Mapping[str, str], body: bytes | None) -> R:
    merged: dict[str, Any] = unpack_body(body) if body else {}
    both = sorted(k for k in params if k in merged)
    if both:
        raise QueryError("bad_parameter", f"parameter {both[0][:40]!r} is given more than "
                                          "once (in the selector and in the body)",
                         both[0][:40])
    try:
        if params:
            from_selector = cls.model_validate_strings(dict(params))
            merged.update({k: getattr(from_selector, k) for k in params})
        return cls.model_validate(merged)
    except ValidationError as exc:
        err = validation_error_to_decode_error(exc)
        raise QueryError("bad_parameter", err.message, err.parameter) from None
    except (TypeError, ValueError, OverflowError) as exc:  # defensive: never escape as-is
        raise QueryError("bad_parameter", str(exc)) from None


def window_of(req: WindowRequest, tiled: TiledMap, n_layers: int,
              admission: Admission | None = None,
              reply_layers: int | None = None) -> GridGeometry:
    """The request's window geometry, priced first by ``admission`` (world, cells returned and
    read for ``n_layers`` sampled layers, reply bytes for ``reply_layers`` planes, default
    ``n_layers``), so a refused window is never built.

    The server always passes its admission: it is the one place a query is priced.  In-process
    callers that build their own windows (tests, benchmarks) may pass none."""
    if admission is not None:
        admission.check_query(req, n_layers, reply_layers=reply_layers)
    res = req.resolution or tiled.lattice.resolution
    return window_geometry(req.x, req.y, req.yaw, req.width, req.height, res)


def resolve_layers(tiled: TiledMap, wanted: list[str] | None) -> list[LayerClass]:
    """The planes of the reply (default: every layer, each its own): an exact name is that
    layer, a glob pattern the class of its matching layers (:mod:`sogm_service.core.classes`).
    A name that is not a layer, or a pattern that matches none, is ``unknown_layer``."""
    names = list(tiled.layers)
    if not wanted:
        return [LayerClass(n, (n,)) for n in names]
    try:
        return cls_.resolve(wanted, names)
    except cls_.NoMatchingLayerError as exc:
        raise _refused(QueryError("unknown_layer", f"no layer matches {list(exc.unmatched)[:8]}; "
                                  f"the map has {names[:32]}", "layers")) from None


def sample_classes(tiled: TiledMap, req: WindowRequest, classes: list[LayerClass],
                   admission: Admission | None = None
                   ) -> tuple[GridGeometry, npt.NDArray[np.int16]]:
    """The window, priced first (the member layers sampled, the classes replied), and one
    plane per class: its member layers sampled once each, then fused (Bayesian, clamped)."""
    members = cls_.member_layers(classes)
    window = window_of(req, tiled, len(members), admission, reply_layers=len(classes))
    stack = tiled.sample(window, members, req.interp)
    if all(len(c.members) == 1 for c in classes) and [c.name for c in classes] == members:
        return window, stack  # exact names, each once: the sample is the reply
    return window, cls_.fuse_classes(stack, members, classes, limits=tiled.limits)


def class_members(classes: list[LayerClass]) -> dict[str, list[str]] | None:
    """A reply's ``classes`` field: each pattern's member layers (None without patterns)."""
    pooled = {c.name: list(c.members) for c in classes if cls_.is_pattern(c.name)}
    return pooled or None


def _placement(tiled: TiledMap, window: GridGeometry, classes: list[LayerClass],
               stamp: float) -> dict[str, Any]:
    """The fields every window reply shares (:class:`~sogm_service.wire.messages.WindowReply`):
    the planes named by the classes, and each pattern's members."""
    return dict(map=tiled.name, frame=tiled.frame, stamp=stamp, resolution=window.resolution,
                origin=PoseModel(x=window.origin.x, y=window.origin.y, yaw=window.origin.yaw),
                width=window.width, height=window.height, layers=[c.name for c in classes],
                classes=class_members(classes))


def submap(tiled: TiledMap, req: SubmapRequest, stamp: float,
           admission: Admission | None = None) -> GridReply:
    """The ``submap`` queryable: the chosen layers resampled into the requested window, a
    pattern's class as one plane named by the pattern."""
    classes = resolve_layers(tiled, req.layers)
    window, stack = sample_classes(tiled, req, classes, admission)
    data = logodds.encode_fixed(stack, req.encoding)
    return GridReply(**_placement(tiled, window, classes, stamp), encoding=req.encoding,
                     interp=req.interp, data=WireArray.from_array(data))


def fuse_layers(stack: npt.NDArray[np.int16], method: str) -> npt.NDArray[np.int32]:
    """Eq. 6 over axis 0: ``bayes`` (P_B, sum of log-odds) or ``max`` (P_M)."""
    if method == "bayes":
        return logodds.fuse_bayes(stack)
    return logodds.fuse_max(stack).astype(np.int32)


def fused(tiled: TiledMap, req: FusedRequest, stamp: float,
          admission: Admission | None = None) -> FusedReply:
    """The ``fused`` queryable: one layer pooled from the chosen ones by Eq. 6 (a pattern's
    class counts as one layer, its members fused by the Bayesian rule first)."""
    classes = resolve_layers(tiled, req.layers)
    if not classes:
        raise QueryError("unknown_layer", "the map has no layers yet", "layers")
    window, stack = sample_classes(tiled, req, classes, admission)
    data = logodds.encode_fixed(fuse_layers(stack, req.method), req.encoding)
    return FusedReply(**_placement(tiled, window, classes, stamp), method=req.method,
                      encoding=req.encoding, interp=req.interp,
                      data=WireArray.from_array(data))


def supercell_input(tiled: TiledMap, req: SupercellRequest,
                    admission: Admission | None = None
                    ) -> tuple[GridGeometry, list[LayerClass], npt.NDArray[np.int16]]:
    """The window, its classes and their log-odds: all the ``supercells`` query needs from the
    map (the server holds its map lock only for this part, not for SEVDS)."""
    classes = price_supercells(tiled, req, admission)
    window, stack = sample_classes(tiled, req, classes, None)  # priced just above
    return window, classes, stack


def price_supercells(tiled: TiledMap, req: SupercellRequest,
                     admission: Admission | None = None) -> list[LayerClass]:
    """The classes of a ``supercells`` query, its window priced and checked against one block:
    arithmetic on the request and the layer names only, so the server refuses a bad query
    before it waits for the kernels or a heavy slot."""
    classes = resolve_layers(tiled, req.layers)
    if not classes:
        raise QueryError("unknown_layer", "the map has no layers yet", "layers")
    geometry = window_of(req, tiled, len(cls_.member_layers(classes)), admission,
                         reply_layers=len(classes))
    if min(geometry.width, geometry.height) < req.block_size:
        raise QueryError("bad_parameter", f"the window ({geometry.width}x{geometry.height} "
                                          f"cells) is smaller than one block "
                                          f"({req.block_size})", "block_size")
    return classes


def supercells(tiled: TiledMap, req: SupercellRequest, window: GridGeometry,
               layers: list[LayerClass], stack: npt.NDArray[np.int16],
               stamp: float) -> SupercellReply:
    """The ``supercells`` queryable: SEVDS (Eq. 7-10) on the window, as a topometric graph.

    Each node is the paper's triple (T_c, L_c, P_c): its place in the map frame (the supercell's
    cell nearest its centroid, so inside it), adjacent supercells, and the Eq. 11 feature vector
    (summed log-odds per layer, plus mean P).
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
    nodes = [SupercellNode(id=k, x=float(graph.positions[k, 0]), y=float(graph.positions[k, 1]),
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
