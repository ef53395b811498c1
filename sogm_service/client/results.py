"""What the client's queries return and how replies become results: a sub-map or fused map with
its geometry (:class:`GridResult`), built from a grid reply, and the :class:`ServiceError` an
error reply raises.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.wire import codec
from sogm_service.wire.errors import DecodeError, ServiceError
from sogm_service.wire.messages import ErrorReply
from sogm_service.wire.queries import FusedReply, GridReply


@dataclass(frozen=True)
class GridResult:
    """A sub-map or fused map: ``data`` is ``(layers, H, W)`` (fused: ``(H, W)``).

    A glob pattern among the layers asked names a class, one plane of ``data``; ``classes``
    gives each pattern's member layers (empty without a pattern)."""

    geometry: GridGeometry
    layers: list[str]
    encoding: str
    data: npt.NDArray[Any]
    stamp: float
    method: str | None = None
    classes: dict[str, list[str]] = field(default_factory=dict)

    def probabilities(self) -> npt.NDArray[np.float32]:
        """The cells as probabilities whatever the reply encoding (unknown -> 0.5)."""
        return logodds.decode_to_prob(self.data, self.encoding)


def grid_result(reply: GridReply | FusedReply) -> GridResult:
    """A sub-map or fused-map reply as a result placed by its geometry."""
    geometry = GridGeometry(reply.resolution, reply.width, reply.height,
                            Pose2D(reply.origin.x, reply.origin.y, reply.origin.yaw))
    method = reply.method if isinstance(reply, FusedReply) else None
    return GridResult(geometry, list(reply.layers), reply.encoding, reply.data.array(),
                      reply.stamp, method, dict(reply.classes or {}))


def service_error(payload: bytes) -> ServiceError:
    """The error an error reply carries (its code, message, parameter and retry hint); a reply
    that does not decode becomes ``ServiceError('unknown')`` with the start of its bytes."""
    try:
        err = codec.decode(ErrorReply, payload)
    except DecodeError:
        return ServiceError("unknown", payload[:200].decode("utf-8", "replace"))
    exc = ServiceError(err.code, err.message, err.parameter)
    exc.retry_after_s = err.retry_after_s
    return exc
