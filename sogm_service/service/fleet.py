"""Following the fleet: the tile manager fed by poses and ISMs (DESIGN.md section 3).

The :class:`~sogm_service.core.tilemanager.TileManager` follows each robot's pose (``pose/**``,
or the centre of the robot's ISMs while it sends no poses).  When a robot switches tile a
:class:`~sogm_service.wire.messages.TileEvent` is published on ``<prefix>/<map>/events/tile``,
the tiles entering a region of interest are preloaded and those that left every region are
checkpointed.  ``<prefix>/<map>/robots`` answers late joiners with each robot's current tile.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from sogm_service.core.geometry import TileLattice
from sogm_service.core.tilemanager import TileManager, TileSwitchEvent
from sogm_service.core.tiletypes import TileIndex
from sogm_service.service.checkpoints import Checkpointer
from sogm_service.service.config import ServiceConfig
from sogm_service.service.stats import Stats
from sogm_service.wire.messages import GeodeticFix, PoseModel, RobotTilesReply, TileEvent

Publish = Callable[[TileEvent], None]


class FleetTracker:
    """Robots' current tiles, tile-switch events and regions of interest (thread-safe)."""

    def __init__(self, config: ServiceConfig, lattice: TileLattice, stats: Stats) -> None:
        self.config = config
        self.stats = stats
        self.manager = TileManager(lattice, config.tiles.hysteresis_m,
                                   config.tiles.roi_radius_tiles, datum=config.map.datum,
                                   map_name=config.map.name)
        self._lock = threading.Lock()
        self._posed: set[str] = set()
        self._positions: dict[str, tuple[float, float]] = {}
        self._publish: Publish | None = None
        self._tiles: Checkpointer | None = None

    def attach(self, publish: Publish, tiles: Checkpointer) -> None:
        """Events go out through ``publish``; ROI changes preload and persist through ``tiles``."""
        self._publish, self._tiles = publish, tiles

    def regions_of_interest(self) -> set[TileIndex]:
        with self._lock:
            return self.manager.regions_of_interest()

    def robot_pose(self, robot: str, x: float, y: float, stamp: float) -> None:
        """A robot's pose from ``pose/**``: from now on the manager follows its poses only."""
        with self._lock:
            self._posed.add(robot)
        self._follow(robot, x, y, stamp)

    def ism_centre(self, robot: str | None, x: float, y: float, stamp: float) -> None:
        """An ISM of ``robot`` centred at ``(x, y)``: followed while the robot sends no pose."""
        if not robot:
            return
        with self._lock:
            posed = robot in self._posed
        if not posed:
            self._follow(robot, x, y, stamp)

    def _follow(self, robot: str, x: float, y: float, stamp: float) -> None:
        with self._lock:
            self._positions[robot] = (x, y)
            event = self.manager.update(robot, x, y, stamp)
            entered, left = self.manager.roi_changes() if event else (set(), set())
        if event is None:
            return
        self.stats.count("tile_switches")
        if self._publish is not None:
            self._publish(self.tile_event(event))
        if self._tiles is not None:
            self._tiles.preload(entered)
            self._tiles.persist(left)

    def tile_event(self, event: TileSwitchEvent) -> TileEvent:
        datum = None if event.datum is None else GeodeticFix(**event.datum.as_dict())
        return TileEvent(map=self.config.map.name, robot=event.robot, i=event.index[0],
                         j=event.index[1], name=event.name,
                         origin=PoseModel(x=event.origin.x, y=event.origin.y, yaw=0.0),
                         datum=datum, stamp=event.stamp)

    def robots_reply(self) -> RobotTilesReply:
        """Each robot's current tile (its last tile-switch event)."""
        with self._lock:
            events = [self.tile_event(e) for e in self.manager.current_tiles().values()]
        return RobotTilesReply(map=self.config.map.name, robots=events)

    def positions(self) -> list[tuple[float, float]]:
        """Each robot's last known position (map frame)."""
        with self._lock:
            return list(self._positions.values())

    def robot_count(self) -> int:
        with self._lock:
            return len(self.manager.current_tiles())
