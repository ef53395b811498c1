"""The tile manager: which tile each robot is in, and which tiles the fleet needs (pure, no I/O).

This is the paper's *tile publisher* (section III-E) on a fixed lattice
(:class:`~sogm_service.core.geometry.TileLattice`; architecture, section 4:
docs/architecture.md#4-maps-and-tiles).  Unlike the paper, a switch
moves no map content: every tile keeps its place in the map frame, and the switch only tells
listeners (and the server's persistence) where each robot now works.

Hysteresis.  A robot's *current tile* changes only when the robot leaves that tile expanded by
the margin ``h`` on every side, i.e. once it is ``h`` metres past the tile's edge (equivalently:
``h`` metres inside the inner boundary of the neighbour).  A robot driving along an edge, or
jittering across it by less than ``h``, therefore keeps its tile.  After a switch the new tile is
simply the lattice tile containing the robot, and the same rule applies from there.  A pose jump
(relocalisation) of any length is handled the same way.

Regions of interest.  The ROI of a robot is the square of ``(2r + 1)^2`` tiles centred on its
*current* tile (Chebyshev radius ``r`` in tiles).  Using the hysteresis-stable current tile rather
than the raw position keeps the ROI from flapping too; with ``r >= 1`` the neighbour a robot is
about to enter is always preloaded.  The fleet's ROI is the union over robots.

Geo-referencing: when a datum is configured, each event carries the WGS-84 position of its tile's
origin corner (:mod:`sogm_service.core.geodesy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sogm_service.core.geodesy import GeodeticLike, GeoPoint, LocalTangentPlane
from sogm_service.core.geometry import Pose2D, TileLattice
from sogm_service.core.map.tiletypes import TileIndex, tile_name


@dataclass(frozen=True, slots=True)
class TileSwitchEvent:
    """A robot entered a new current tile (or was seen for the first time)."""

    robot: str
    index: TileIndex
    name: str
    origin: Pose2D
    """Pose of the tile's corner of cell (0, 0) in the map frame (yaw always 0)."""
    stamp: float
    datum: GeoPoint | None = None
    """WGS-84 position of the tile origin when the map is geo-referenced."""
    previous: TileIndex | None = None
    """The robot's previous current tile; ``None`` for a robot's first pose."""

    def as_dict(self) -> dict[str, Any]:
        """Plain types for a wire message."""
        return {
            "robot": self.robot, "i": self.index[0], "j": self.index[1], "name": self.name,
            "origin": {"x": self.origin.x, "y": self.origin.y, "yaw": self.origin.yaw},
            "stamp": self.stamp,
            "datum": None if self.datum is None else self.datum.as_dict(),
            "previous": None if self.previous is None else list(self.previous),
        }


def hysteresis_from_fraction(lattice: TileLattice, fraction: float) -> float:
    """A hysteresis margin given as a fraction of the tile span, in metres."""
    if not (math.isfinite(fraction) and 0.0 <= fraction < 1.0):
        raise ValueError(f"hysteresis fraction must lie in [0, 1), got {fraction}")
    return fraction * lattice.span


class TileManager:
    """Follows every robot's pose on the tile lattice; see the module docstring.

    Not thread-safe: the server calls it under its own lock (or from one worker).
    """

    def __init__(self, lattice: TileLattice, hysteresis_m: float, roi_radius_tiles: int,
                 datum: GeodeticLike | None = None, map_name: str = "default") -> None:
        if not (math.isfinite(hysteresis_m) and 0.0 <= hysteresis_m < lattice.span):
            raise ValueError(f"hysteresis must lie in [0, {lattice.span}) m (one tile), "
                             f"got {hysteresis_m}")
        if roi_radius_tiles < 0:
            raise ValueError(f"ROI radius must be >= 0 tiles, got {roi_radius_tiles}")
        self.lattice = lattice
        self.hysteresis_m = float(hysteresis_m)
        self.roi_radius_tiles = int(roi_radius_tiles)
        self.map_name = map_name
        self.plane = None if datum is None else LocalTangentPlane(datum)
        self._current: dict[str, TileSwitchEvent] = {}
        self._reported_roi: set[TileIndex] = set()

    # -- poses ----------------------------------------------------------------------------
    def update(self, robot: str, x: float, y: float, stamp: float) -> TileSwitchEvent | None:
        """Feed one pose (map frame); return the switch event if the current tile changed.

        A robot's first pose always yields an event.  Non-finite positions are rejected with
        ``ValueError`` (the caller counts them as bad input) and change nothing.
        """
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"pose of {robot!r} is not finite: ({x}, {y})")
        now = self._current.get(robot)
        if now is not None and self._inside_band(now.index, x, y):
            return None
        event = self.make_event(robot, self.lattice.tile_of(x, y), stamp,
                                None if now is None else now.index)
        self._current[robot] = event
        return event

    def _inside_band(self, index: TileIndex, x: float, y: float) -> bool:
        """Whether ``(x, y)`` lies in tile ``index`` grown by the hysteresis margin."""
        span, h = self.lattice.span, self.hysteresis_m
        x0, y0 = index[0] * span, index[1] * span
        return (x0 - h <= x < x0 + span + h) and (y0 - h <= y < y0 + span + h)

    def make_event(self, robot: str, index: TileIndex, stamp: float,
                   previous: TileIndex | None = None) -> TileSwitchEvent:
        """The event describing tile ``index`` for ``robot`` (name, origin, datum)."""
        origin = self.lattice.tile_origin(*index)
        return TileSwitchEvent(robot=robot, index=index,
                               name=tile_name(self.map_name, *index), origin=origin,
                               stamp=stamp, datum=self.tile_datum(*index), previous=previous)

    def tile_datum(self, i: int, j: int) -> GeoPoint | None:
        """WGS-84 position of tile ``(i, j)``'s origin corner, or None without a map datum."""
        if self.plane is None:
            return None
        origin = self.lattice.tile_origin(i, j)
        return self.plane.to_geodetic(origin.x, origin.y)

    def remove(self, robot: str) -> bool:
        """Forget a robot (e.g. its liveliness token vanished); its ROI goes with it."""
        return self._current.pop(robot, None) is not None

    # -- queries --------------------------------------------------------------------------
    def current_tiles(self) -> dict[str, TileSwitchEvent]:
        """The last switch event of every known robot (what a late joiner needs)."""
        return dict(self._current)

    def current_tile(self, robot: str) -> TileIndex | None:
        event = self._current.get(robot)
        return None if event is None else event.index

    def roi_of(self, index: TileIndex) -> set[TileIndex]:
        """The ``(2r + 1)^2`` tiles around ``index``."""
        r = self.roi_radius_tiles
        i, j = index
        return {(i + di, j + dj) for di in range(-r, r + 1) for dj in range(-r, r + 1)}

    def regions_of_interest(self) -> set[TileIndex]:
        """Union of every robot's ROI."""
        out: set[TileIndex] = set()
        for event in self._current.values():
            out |= self.roi_of(event.index)
        return out

    def roi_changes(self) -> tuple[set[TileIndex], set[TileIndex]]:
        """``(entered, left)``: tiles that joined / left the fleet's ROI since the last call.

        The first call reports the whole current ROI as entered.  The server preloads the
        entered tiles and persists (then may evict) the left ones.
        """
        roi = self.regions_of_interest()
        entered, left = roi - self._reported_roi, self._reported_roi - roi
        self._reported_roi = roi
        return entered, left
