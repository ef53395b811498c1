"""From a validated ISM message to a Bayesian update of the tiled map (pure, no I/O).

Flow (DESIGN.md section 2): decoded/validated :class:`~sogm_service.messages.IsmMessage` ->
fixed log-odds increments (256-entry lookup table for 8-bit encodings) -> resampled from the
ISM's own pose and resolution into each tile it overlaps -> Eq. 1 add-then-clamp.
"""

from __future__ import annotations

import re

from sogm_service import logodds
from sogm_service.geometry import GridGeometry, Pose2D
from sogm_service.messages import IsmMessage
from sogm_service.resample import Interp
from sogm_service.tiles import TiledMap, TileIndex

_LAYER_NAME = re.compile(r"^[A-Za-z0-9_\-./]{1,128}$")


class IsmRejectedError(ValueError):
    """An ISM that is well-formed on the wire but cannot go into this map."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def key_prefix(key_expr: str) -> str:
    """The literal chunks of a key expression before its first wildcard (``ism/**`` -> ``ism``)."""
    literal = []
    for chunk in key_expr.split("/"):
        if "*" in chunk or "$" in chunk:
            break
        literal.append(chunk)
    return "/".join(literal)


def layer_name(msg: IsmMessage, key: str, key_expr: str) -> str:
    """The ISM's layer: its ``layer`` field, else the key's remainder after the literal prefix."""
    name = msg.layer
    if not name:
        prefix = key_prefix(key_expr)
        name = key[len(prefix):].strip("/") if prefix and key.startswith(prefix) else key
    if not _LAYER_NAME.match(name):
        raise IsmRejectedError("bad_layer", f"layer name {name!r} is empty, too long or has "
                                       "characters outside [A-Za-z0-9_-./]")
    return name


def ism_geometry(msg: IsmMessage) -> GridGeometry:
    return GridGeometry(msg.resolution, msg.width, msg.height,
                        Pose2D(msg.origin.x, msg.origin.y, msg.origin.yaw))


def fuse_ism(tiled: TiledMap, msg: IsmMessage, layer: str, interp: Interp = "biodds",
             geometry: GridGeometry | None = None) -> list[TileIndex]:
    """Eq. 1 for one ISM; ``geometry`` overrides the message's (e.g. after scan matching)."""
    if msg.frame != tiled.frame:
        raise IsmRejectedError("wrong_frame",
                          f"ISM frame {msg.frame!r} is not the map frame {tiled.frame!r}")
    inc = logodds.increments(msg.array(), msg.encoding, tiled.eps0)
    return tiled.fuse(layer, inc, geometry or ism_geometry(msg), interp, msg.stamp)
