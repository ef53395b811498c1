"""From a validated ISM message to a Bayesian update of the tiled map (pure, no I/O).

Flow (DESIGN.md section 2): decoded/validated :class:`~sogm_service.wire.messages.IsmMessage` ->
fixed log-odds increments (256-entry lookup table for 8-bit encodings) -> resampled from the
ISM's own pose and resolution into each tile it overlaps -> Eq. 1 add-then-clamp.
"""

from __future__ import annotations

import re
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.matching import (
    MatchParams,
    MatchResult,
    corrected_geometry,
    match_ism,
    match_window,
    prior_matrix,
)
from sogm_service.core.resample import Interp, resample_logodds
from sogm_service.core.tiles import TiledMap, TileIndex
from sogm_service.wire.errors import IsmRejectedError
from sogm_service.wire.keys import key_remainder
from sogm_service.wire.limits import LAYER_NAME_PATTERN
from sogm_service.wire.messages import IsmMessage

_LAYER_NAME = re.compile(LAYER_NAME_PATTERN)


def layer_name(msg: IsmMessage, key: str, key_expr: str) -> str:
    """The ISM's layer: its ``layer`` field, else the key's remainder after the literal prefix."""
    name = msg.layer
    if not name:
        name = key_remainder(key, key_expr)
    if not _LAYER_NAME.match(name):
        raise IsmRejectedError("bad_layer", f"layer name {name!r} is empty, too long or has "
                                       "characters outside [A-Za-z0-9_-./]")
    return name


def ism_geometry(msg: IsmMessage) -> GridGeometry:
    return GridGeometry(msg.resolution, msg.width, msg.height,
                        Pose2D(msg.origin.x, msg.origin.y, msg.origin.yaw))


def fuse_ism(tiled: TiledMap, msg: IsmMessage, layer: str,
             interp: Interp = "biodds") -> list[TileIndex]:
    """Eq. 1 for one ISM, as it claims to be placed."""
    inc, geometry = prepare(tiled, msg)
    return tiled.fuse(layer, inc, geometry, interp, msg.stamp)


def prepare(tiled: TiledMap, msg: IsmMessage) -> tuple[npt.NDArray[np.int16], GridGeometry]:
    """Check the frame; the ISM's fixed log-odds increments and its geometry."""
    if msg.frame != tiled.frame:
        raise IsmRejectedError("wrong_frame",
                               f"ISM frame {msg.frame!r} is not the map frame {tiled.frame!r}")
    return logodds.increments(msg.array(), msg.encoding, tiled.eps0), ism_geometry(msg)


def check_extent(tiled: TiledMap, geometry: GridGeometry, max_tiles: int) -> None:
    """Refuse an ISM whose footprint would touch more than ``max_tiles`` tiles (a valid but
    absurd resolution could otherwise create millions of tiles)."""
    n = len(tiled.lattice.tiles_overlapping(geometry))
    if n > max_tiles:
        raise IsmRejectedError("too_large", f"the ISM covers {n} tiles; the limit is "
                                            f"{max_tiles} (check its resolution)")


@dataclass(frozen=True)
class Alignment:
    """The outcome of scan matching one ISM against the map (paper section III-C.2)."""

    result: MatchResult | None  # None: skipped (nothing in the map to match against yet)
    increments: npt.NDArray[np.int16]  # the ISM at map resolution, in its own frame
    claimed: GridGeometry  # where the ISM says it is (map resolution)
    corrected: GridGeometry | None  # where matching put it (when accepted)


def align(tiled: TiledMap, inc: npt.NDArray[np.int16], geometry: GridGeometry,
          layer: str, params: MatchParams, min_known: int,
          map_lock: AbstractContextManager[Any] | None = None) -> Alignment:
    """Match an ISM against the map window around its claimed pose.

    The ISM is first brought to map resolution in its own frame (matching needs one scale);
    the window is the claimed footprint plus the matcher's margin, sampled from ``layer``.
    ``map_lock`` is held only while the map is read, not while features are matched.
    """
    res = tiled.lattice.resolution
    claimed = GridGeometry(res, max(1, round(geometry.width * geometry.resolution / res)),
                           max(1, round(geometry.height * geometry.resolution / res)),
                           geometry.origin)
    ism = inc if claimed == geometry else resample_logodds(inc, geometry, claimed, "biodds")
    window = match_window(claimed, params)
    with map_lock or nullcontext():
        if layer not in tiled.layers:
            return Alignment(None, ism, claimed, None)
        surroundings = tiled.sample(window, [layer], "biodds")[0]
    if np.count_nonzero(surroundings) < min_known:
        return Alignment(None, ism, claimed, None)
    result = match_ism(ism, surroundings, params, prior_matrix(claimed, window))
    corrected = corrected_geometry(claimed, window, result) if result.accepted else None
    return Alignment(result, ism, claimed, corrected)
