"""ROS 2 robots and tools on the map server, over rmw_zenoh's wire (``[ros2] enabled``).

The :class:`~sogm_service.service.ros2.bridge.Ros2Bridge` speaks rmw_zenoh (CDR, attachments,
liveliness tokens); this part wires it to the server: an ``OccupancyGrid`` ISM goes into the
same ingestion queue as a native one (and from there through the same pipeline, limits,
counters and rejection reasons), poses drive the fleet tracker, and a thread republishes the
map every ``publish_period_s`` over a stable extent (the bridge sends only what changed: whole
grids or ``OccupancyGridUpdate`` rectangles), with nav2's filter masks of ``[nav2]`` over the
same extent.  Imported only when
enabled: the ``ros2`` extra (rosbags, xxhash) is needed then and only then.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace
from typing import Any

import zenoh

from sogm_service.adapters.ros2.extent import (
    GROWTH_STEP_CELLS,
    HEADROOM,
    RegionTracker,
    geometry_of,
    publish_region,
    shrink_about_centre,
    stable_extent,
)
from sogm_service.adapters.ros2.filters import FilterSpec, filter_masks
from sogm_service.adapters.ros2.views import MapSnapshot, map_snapshot
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.config import ServiceConfig
from sogm_service.service.ros2.bridge import Ros2Bridge
from sogm_service.service.ros2.settings import Ros2BridgeSettings
from sogm_service.service.server.fleet import FleetTracker
from sogm_service.service.server.ingest import IngestQueue
from sogm_service.service.server.pipeline import IsmItem
from sogm_service.service.server.stats import Rejections, Stats
from sogm_service.wire.messages import IsmMessage

log = logging.getLogger(__name__)


def filter_spec(config: ServiceConfig) -> FilterSpec:
    """nav2's filter masks of ``[nav2]``."""
    n = config.nav2
    return FilterSpec(keepout=tuple(n.keepout), keepout_threshold=n.keepout_threshold,
                      speed=dict(n.speed), speed_threshold=n.speed_threshold)


def bridge_settings(config: ServiceConfig) -> Ros2BridgeSettings:
    r = config.ros2
    return Ros2BridgeSettings(
        domain=r.domain, ism_prefix=r.ism_prefix, pose_topics=tuple(r.pose_topics),
        odom_topics=tuple(r.odom_topics), tf_topics=tuple(r.tf_topics),
        tf_static_topics=tuple(r.tf_static_topics), map_frame=config.map.frame,
        robot_frame=r.robot_frame, humble=r.humble, topic_root=r.topic_root,
        node_name=r.node_name, max_payload_bytes=config.limits.max_payload_bytes,
        max_cells=config.limits.max_ism_cells, max_tilt=r.max_tilt_rad,
        full_period_s=r.full_period_s, whole_masks=config.nav2.whole_masks)


class Ros2Link:
    """The bridge, its callbacks into the server, and the map publication thread."""

    def __init__(self, config: ServiceConfig, session: zenoh.Session, tiled: TiledMap,
                 queue: IngestQueue, fleet: FleetTracker, stats: Stats,
                 rejections: Rejections) -> None:
        self.config = config
        self.tiled = tiled
        self.queue = queue
        self.fleet = fleet
        self.stats = stats
        self.rejections = rejections
        self._stop = threading.Event()
        self.extent: GridGeometry | None = None  # the published extent: it only grows
        self._changes = RegionTracker()
        self.filters = filter_spec(config)
        self.bridge = Ros2Bridge(session, map_name=config.map.name,
                                 settings=bridge_settings(config), on_ism=self._on_ism,
                                 on_pose=self._on_pose, on_reject=self._on_reject,
                                 map_source=self.snapshot)
        self._thread = threading.Thread(target=self._publish_loop, name="sogm-ros2",
                                        daemon=True)
        self._thread.start()
        log.info("ROS 2: domain %d, ISMs under %s, maps on %s", config.ros2.domain,
                 config.ros2.ism_prefix, self.bridge.map_topic)

    def _on_ism(self, key: str, layer: str, msg: IsmMessage) -> None:
        self.stats.count("isms_received")
        self.queue.put(IsmItem(self.config.ros2.ism_source, key, msg=msg, layer=layer,
                               robot=msg.robot))

    def _on_pose(self, robot: str, x: float, y: float, yaw: float, stamp: float) -> None:
        self.stats.count("poses_received")
        self.fleet.submit_pose(robot, x, y, stamp)  # priced, queued, counted as any pose

    def _on_reject(self, what: str, code: str, text: str) -> None:
        if what == "ism":  # received and refused, as a native bad ISM
            self.stats.count("isms_received")
            self.rejections.reject(code, text)
        else:
            self.stats.count(f"ros2_{what}_rejected_{code}")

    def snapshot(self) -> MapSnapshot:
        """The layers and the fused map over the published extent (the publication region
        made stable by :func:`~sogm_service.adapters.ros2.extent.stable_extent`: it grows with
        headroom and never moves while it holds the region's centre), sampled, pooled and
        converted by :func:`~sogm_service.adapters.ros2.views.map_snapshot`."""
        window = self._region()
        if window is not None:
            r = self.config.ros2
            self.extent = stable_extent(self.extent, window, step=GROWTH_STEP_CELLS,
                                        max_cells=r.max_publish_cells, headroom=HEADROOM)
        if self.extent is None:
            return MapSnapshot()
        r = self.config.ros2
        now = time.time()
        snap = map_snapshot(self.tiled, self.extent, stamp=now, layers=r.layers,
                            fused_layers=r.fused_layers, method=r.fused_method,
                            publish_layers=r.publish_layers)
        if not self.filters.enabled:
            return snap
        # nav2's filter masks over the same extent (:mod:`...adapters.ros2.filters`)
        return replace(snap, masks=filter_masks(self.tiled, self.extent, self.filters,
                                                stamp=now))

    def _region(self) -> GridGeometry | None:
        """What the published extent must hold now (``[ros2] region``); None: nothing new."""
        r = self.config.ros2
        if r.region != "recent":
            return publish_region(self.tiled, self.fleet.positions(), mode=r.region,
                                  radius_m=r.region_radius_m, max_cells=r.max_publish_cells)
        changed = self._changes.changed(self.tiled)
        if changed is None:
            return None
        return geometry_of(shrink_about_centre(changed, r.max_publish_cells),
                           self.tiled.lattice.resolution)

    def _publish_loop(self) -> None:
        while not self._stop.wait(self.config.ros2.publish_period_s):
            try:
                self.bridge.publish_maps()
            except Exception:  # never let a publication failure end the loop
                log.exception("ROS 2 map publication failed")

    def stats_extra(self) -> dict[str, Any]:
        return {"ros2": self.bridge.stats()}

    def close(self, timeout: float) -> None:
        self._stop.set()
        self._thread.join(timeout)
        self.bridge.close()
