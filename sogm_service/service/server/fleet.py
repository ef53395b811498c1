"""Following the fleet: the tile manager fed by poses and ISMs (architecture, section 4:
docs/architecture.md#4-maps-and-tiles).

The :class:`~sogm_service.core.map.tilemanager.TileManager` follows each robot's pose (``pose/**``,
or the centre of the robot's ISMs while it sends no poses).  When a robot switches tile a
:class:`~sogm_service.wire.messages.TileEvent` is published on ``<prefix>/<map>/events/tile``,
the tiles entering a region of interest are preloaded and those that left every region are
checkpointed.  ``<prefix>/<map>/robots`` answers late joiners with each robot's current tile.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.footprint import point_in_world
from sogm_service.core.map.tilemanager import TileManager, TileSwitchEvent
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.stats import Stats
from sogm_service.wire.errors import IsmRejectedError
from sogm_service.wire.messages import GeodeticFix, PoseModel, RobotTilesReply, TileEvent

log = logging.getLogger(__name__)

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
        self._admitted: set[str] = set()  # every robot followed or about to be (max_robots)
        # poses waiting for the pose worker, in arrival order; coalesced latest-per-robot
        # whenever more than max_pending_poses wait (memory stays O(limit + robots))
        self._pending: list[tuple[str, float, float, float]] = []
        self._coalesce_at = config.limits.max_pending_poses
        self._pose_cond = threading.Condition()
        self._pose_thread: threading.Thread | None = None
        self._closed = False

    def attach(self, publish: Publish, tiles: Checkpointer) -> None:
        """Events go out through ``publish``; ROI changes preload and persist through ``tiles``."""
        self._publish, self._tiles = publish, tiles

    def regions_of_interest(self) -> set[TileIndex]:
        with self._lock:
            return self.manager.regions_of_interest()

    def ism_centre(self, robot: str | None, x: float, y: float, stamp: float) -> None:
        """An ISM of ``robot`` centred at ``(x, y)``: followed while the robot sends no pose."""
        if not robot:
            return
        with self._lock:
            posed = robot in self._posed
        if not posed:
            with self._lock:
                self._admitted.add(robot)
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

    # -- admission and pose coalescing ----------------------------------------------------
    def check_robot(self, robot: str) -> None:
        """Refuse a robot that would be one more than ``max_robots`` (``too_many_robots``)."""
        with self._lock:
            self._refuse_beyond_limit(robot)

    def _refuse_beyond_limit(self, robot: str) -> None:
        limit = self.config.limits.max_robots
        if robot in self._admitted or len(self._admitted) < limit:
            return
        raise IsmRejectedError("too_many_robots", f"{limit} robots are tracked, the limit; "
                               f"refusing robot {robot[:64]!r}", "robot")

    def submit_pose(self, robot: str, x: float, y: float, stamp: float) -> bool:
        """A checked pose, queued for the pose worker: O(1) amortised, never blocks on the map.
        Beyond ``max_pending_poses`` waiting, the queue is coalesced latest-per-robot (the
        replaced poses are counted ``poses_coalesced``); a pose of a robot beyond
        ``max_robots`` is ``poses_rejected_too_many_robots``."""
        try:
            lim = self.config.limits
            if len(robot) > lim.max_robot_name:
                raise IsmRejectedError("name_too_long", "robot name too long", "robot")
            if not point_in_world(x, y, lim.world_extent_m):
                raise IsmRejectedError("out_of_world", "pose outside the world", "x")
            with self._lock:
                self._refuse_beyond_limit(robot)
                self._admitted.add(robot)
        except IsmRejectedError as exc:
            self.stats.count("poses_rejected")
            self.stats.count(f"poses_rejected_{exc.code}")
            return False
        with self._pose_cond:
            if self._closed:
                self.stats.count("poses_rejected")
                self.stats.count("poses_rejected_closing")
                return False
            self._pending.append((robot, x, y, stamp))
            if len(self._pending) > self._coalesce_at:
                self._coalesce()
            if self._pose_thread is None:
                self._pose_thread = threading.Thread(target=self._pose_loop,
                                                     name="sogm-poses", daemon=True)
                self._pose_thread.start()
            self._pose_cond.notify()
        return True

    def _coalesce(self) -> None:
        """Keep only each robot's latest waiting pose (in the order of those poses); the next
        coalescing waits for another ``max_pending_poses`` (amortised O(1) a pose)."""
        latest: dict[str, tuple[str, float, float, float]] = {}
        for item in self._pending:
            latest.pop(item[0], None)
            latest[item[0]] = item
        self.stats.count("poses_coalesced", len(self._pending) - len(latest))
        self._pending = list(latest.values())
        self._coalesce_at = len(self._pending) + self.config.limits.max_pending_poses

    def _pose_loop(self) -> None:
        while True:
            with self._pose_cond:
                self._pose_cond.wait_for(lambda: bool(self._pending) or self._closed)
                if not self._pending and self._closed:
                    return
                batch, self._pending = self._pending, []
                self._coalesce_at = self.config.limits.max_pending_poses
            try:
                self._apply_batch(batch)
            except Exception:  # a pose must never end the worker
                log.exception("a batch of %d poses failed", len(batch))
                self.stats.count("poses_rejected", len(batch))
                self.stats.count("poses_rejected_internal_error", len(batch))

    def _apply_batch(self, batch: list[tuple[str, float, float, float]]) -> None:
        """The waiting poses in arrival order (every tile switch is an event), the fleet's
        regions of interest (O(robots)) worked out once per batch, not once per switch."""
        events: list[TileSwitchEvent] = []
        with self._lock:
            for robot, x, y, stamp in batch:
                self._posed.add(robot)
                self._positions[robot] = (x, y)
                event = self.manager.update(robot, x, y, stamp)
                if event is not None:
                    events.append(event)
            entered, left = self.manager.roi_changes() if events else (set(), set())
        self.stats.count("poses_applied", len(batch))
        if not events:
            return
        self.stats.count("tile_switches", len(events))
        if self._publish is not None:
            for event in events:
                self._publish(self.tile_event(event))
        if self._tiles is not None:
            self._tiles.preload(entered)
            self._tiles.persist(left)

    def close(self, timeout: float = 5.0) -> None:
        """Apply the poses still pending, then end the pose worker."""
        with self._pose_cond:
            self._closed = True
            self._pose_cond.notify_all()
            thread = self._pose_thread
        if thread is not None:
            thread.join(timeout)
