"""What the ROS 2 bridge publishes (:class:`MapsOut`): each layer's grid and the fused grid on
latched (TRANSIENT_LOCAL, depth 1) topics, their changes on ``<topic>_updates`` as
``map_msgs/msg/OccupancyGridUpdate``, and the ``nav_msgs/srv/GetMap`` service's replies.

A map topic's whole ``OccupancyGrid`` goes out on the first publication, when the grid's extent
(size, origin, resolution or frame) changes, when the change would cost more than half of a
whole grid, at the first publication after a ROS subscriber of the topic appeared (its
liveliness token), and ``full_period_s`` after the last whole grid, each time only if updates
followed that grid.  A late subscriber gets only the latched grid and the latched last update,
so the whole grid that follows its arrival makes its copy exact one period later; the periodic
one is a safety net for subscribers that declare no token.  Otherwise only the rectangles that
changed since the last publication go out
(:func:`~sogm_service.adapters.ros2.updates.changed_rects`), one update each, on the same QoS.
After a whole grid that follows updates, an empty update (0 x 0) replaces the latched one, so a
late subscriber never gets an update older than the grid it writes it into.
"""

from __future__ import annotations

import logging
import struct
import time

import numpy as np
import zenoh
import zenoh.ext

from sogm_service.adapters.ros2 import cdr
from sogm_service.adapters.ros2.attachment import (
    Attachment,
    encode_attachment,
    gid_of,
    parse_attachment,
)
from sogm_service.adapters.ros2.cdr import GridUpdateFields, OccupancyGridFields
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.filterinfo import FilterInfoFields, encode_filter_info
from sogm_service.adapters.ros2.filters import FILTER_BASE, FILTER_MULTIPLIER, FILTER_TYPES
from sogm_service.adapters.ros2.keys import (
    COSTMAP_FILTER_INFO,
    OCCUPANCY_GRID,
    OCCUPANCY_GRID_UPDATE,
    QOS_LATCHED,
    EntityKind,
    ros_safe_name,
    topic_key,
)
from sogm_service.adapters.ros2.updates import changed_rects, grid_update
from sogm_service.service.ros2.state import BridgeState, Publisher

log = logging.getLogger("sogm_service.service.ros2.bridge")  # one logger for the bridge's parts

HEARTBEAT_PERIOD_S = 1.0
"""rmw_zenoh's RELIABLE + TRANSIENT_LOCAL publishers send a sporadic heartbeat (sequence-number
sequencing, so no Zenoh ``timestamping`` is needed) for subscribers to recover a missed last
sample from the cache."""

UPDATES_SUFFIX = "_updates"
MAX_UPDATE_SHARE = 0.5  # updates covering more than this share of the grid: the whole grid


def _now_ns() -> int:
    return time.time_ns()


def _same_extent(a: OccupancyGridFields, b: OccupancyGridFields) -> bool:
    return (a.frame, a.resolution, a.width, a.height, a.position, a.orientation) == \
        (b.frame, b.resolution, b.width, b.height, b.position, b.orientation)


class MapsOut(BridgeState):
    """The bridge's map publishers and its GetMap service."""

    # -- maps out -------------------------------------------------------------------------
    def layer_topic(self, layer: str) -> str:
        return f"{self.base_topic}/layers/{ros_safe_name(layer)}"

    def mask_topic(self, mask: str) -> str:
        """nav2's filter mask ``mask`` (``keepout``, ``speed``): ``<base>/<mask>_mask``."""
        return f"{self.base_topic}/{mask}_mask"

    def filter_info_topic(self, mask: str) -> str:
        return f"{self.base_topic}/{mask}_filter_info"

    def _publisher(self, topic: str, ros_type: str = OCCUPANCY_GRID) -> Publisher:
        slot = topic if ros_type == OCCUPANCY_GRID else f"{topic} {ros_type}"
        with self._lock:
            pub = self._publishers.get(slot)
            if pub is not None:
                return pub
            s = self.settings
            key = topic_key(s.domain, topic, ros_type)
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session, key, cache=zenoh.ext.CacheConfig(max_samples=QOS_LATCHED.depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD_S),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
            token_key = self._entity_token(EntityKind.PUBLISHER, topic, ros_type, QOS_LATCHED)
            pub = Publisher(topic, key, publisher, self._tokens[token_key], gid_of(token_key))
            self._publishers[slot] = pub
            log.info("ROS 2: advertising %s (%s)", topic, ros_type.rsplit("::", 1)[-1])
            return pub

    def _put(self, pub: Publisher, payload: bytes, counter: str) -> None:
        pub.seq += 1
        pub.publisher.put(payload, attachment=encode_attachment(pub.seq, _now_ns(), pub.gid))
        self._count(counter)
        self._count(counter + "_bytes", len(payload))

    def _put_update(self, topic: str, u: GridUpdateFields) -> None:
        pub = self._publisher(topic + UPDATES_SUFFIX, OCCUPANCY_GRID_UPDATE)
        self._put(pub, cdr.encode_grid_update(u), "updates_published")

    def publish_grid(self, topic: str, grid: OccupancyGridFields, *,
                     force: bool = False, updates: bool = True) -> bool:
        """Publish what changed of ``grid`` on ``topic``: nothing when it equals the last grid
        sent there (unless ``force``), the whole grid or (``updates``) the changed rectangles
        on ``<topic>_updates``.  True when anything was sent."""
        period = self.settings.full_period_s
        now = time.monotonic()
        with self._lock:
            if self._closed:
                return False
            pub = self._publisher(topic)
            last = pub.last
            whole = force or last is None or not _same_extent(last, grid)
            rects = []
            if not whole and last is not None:
                rects = changed_rects(last.data, grid.data)
                due = pub.updates_since_full > 0 and (
                    pub.joined or (period > 0 and now - pub.full_at >= period))
                if not rects and not due:
                    return False
                whole = due or not updates or \
                    sum(r.cells for r in rects) > MAX_UPDATE_SHARE * grid.data.size
            if whole:
                payload = cdr.encode_occupancy_grid(grid)
                pub.whole_bytes = len(payload)
                self._put(pub, payload, "grids_published")
                if pub.updates_since_full:  # the latched update must not predate this grid
                    self._put_update(topic, GridUpdateFields(
                        grid.frame, grid.stamp, 0, 0, 0, 0, np.zeros((0, 0), np.int8)))
                pub.full_at, pub.updates_since_full, pub.joined = now, 0, False
            else:
                for r in rects:
                    self._put_update(topic, grid_update(grid, r))
                pub.updates_since_full += len(rects)
            # what republishing the whole grid at every change would have sent instead
            self._count("whole_equivalent_bytes", pub.whole_bytes)
            pub.last = grid
        return True

    def publish_maps(self) -> int:
        """Ask ``map_source`` and publish what changed; returns how many grids changed (each
        sent whole or as updates)."""
        if self._map_source is None:
            return 0
        snap = self._map_source()
        sent = 0
        for layer, grid in snap.layers.items():
            sent += self.publish_grid(self.layer_topic(layer), grid)
        if snap.fused is not None:
            with self._lock:
                self._last_fused = snap.fused
            sent += self.publish_grid(self.map_topic, snap.fused)
        for mask, grid in snap.masks.items():
            self.publish_filter_info(self.filter_info_topic(mask), FilterInfoFields(
                grid.frame, grid.stamp, FILTER_TYPES[mask], self.mask_topic(mask),
                FILTER_BASE, FILTER_MULTIPLIER))
            sent += self.publish_grid(self.mask_topic(mask), grid,
                                      updates=not self.settings.whole_masks)
        return sent

    def publish_filter_info(self, topic: str, info: FilterInfoFields) -> bool:
        """Publish a CostmapFilterInfo (latched) unless the last one sent on ``topic`` holds
        the same; True when sent."""
        with self._lock:
            if self._closed:
                return False
            pub = self._publisher(topic, COSTMAP_FILTER_INFO)
            if info.same_content(self._filter_infos.get(topic)):
                return False
            self._put(pub, encode_filter_info(info), "filter_infos_published")
            self._filter_infos[topic] = info
        return True

    # -- GetMap ---------------------------------------------------------------------------
    def _on_get_map(self, q: zenoh.Query) -> None:
        self._count("get_map_requests")
        try:
            att = q.attachment
            request: Attachment = parse_attachment(att.to_bytes() if att is not None else None)
            cdr.decode_get_map_request(q.payload.to_bytes() if q.payload is not None
                                       else cdr.CDR_LE_HEADER)
        except Ros2DecodeError as exc:
            self._reject("get_map", exc.code, f"GetMap request {q.selector}: {exc.message}")
            q.reply_err(f"{exc.code}: {exc.message}".encode())
            return
        with self._lock:
            grid = self._last_fused
        if grid is None and self._map_source is not None:
            grid = self._map_source().fused
        if grid is None:  # nothing mapped yet: an empty map, as a map_server without one
            grid = OccupancyGridFields(self.settings.map_frame, time.time(), 0.05, 0, 0,
                                       (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                                       np.zeros((0, 0), np.int8))
        reply_att = _echo_attachment(request)
        q.reply(q.key_expr, cdr.encode_get_map_response(grid), attachment=reply_att)


def _echo_attachment(request: Attachment) -> bytes:
    """A reply's attachment: the request's sequence number and gid, the reply's time."""
    if len(request.gid) == 16:
        return encode_attachment(request.sequence_number, _now_ns(), request.gid)
    # a Humble client's 24-byte gid, echoed as it came
    return struct.pack("<qq", request.sequence_number, _now_ns()) + bytes([len(request.gid)]) \
        + request.gid
