"""What the ROS 2 bridge publishes (:class:`MapsOut`): each layer's grid and the fused grid on
latched (TRANSIENT_LOCAL, depth 1) topics when they change, and the ``nav_msgs/srv/GetMap``
service's replies.
"""

from __future__ import annotations

import hashlib
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
from sogm_service.adapters.ros2.cdr import OccupancyGridFields
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import (
    OCCUPANCY_GRID,
    QOS_LATCHED,
    EntityKind,
    ros_safe_name,
    topic_key,
)
from sogm_service.service.ros2.state import BridgeState, Publisher

log = logging.getLogger("sogm_service.service.ros2.bridge")  # one logger for the bridge's parts

HEARTBEAT_PERIOD_S = 1.0
"""rmw_zenoh's RELIABLE + TRANSIENT_LOCAL publishers send a sporadic heartbeat (sequence-number
sequencing, so no Zenoh ``timestamping`` is needed) for subscribers to recover a missed last
sample from the cache."""


def _now_ns() -> int:
    return time.time_ns()


def _digest(g: OccupancyGridFields) -> bytes:
    """What makes a grid "changed": cells, geometry and frame (not the stamp)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((g.frame, g.resolution, g.width, g.height, g.position,
                   g.orientation)).encode())
    h.update(g.data.tobytes())
    return h.digest()


class MapsOut(BridgeState):
    """The bridge's map publishers and its GetMap service."""

    # -- maps out -------------------------------------------------------------------------
    def layer_topic(self, layer: str) -> str:
        return f"{self.base_topic}/layers/{ros_safe_name(layer)}"

    def _publisher(self, topic: str) -> Publisher:
        with self._lock:
            pub = self._publishers.get(topic)
            if pub is not None:
                return pub
            s = self.settings
            key = topic_key(s.domain, topic, OCCUPANCY_GRID)
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session, key, cache=zenoh.ext.CacheConfig(max_samples=QOS_LATCHED.depth),
                publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD_S),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
            token_key = self._entity_token(EntityKind.PUBLISHER, topic, OCCUPANCY_GRID,
                                           QOS_LATCHED)
            pub = Publisher(topic, key, publisher, self._tokens[token_key], gid_of(token_key))
            self._publishers[topic] = pub
            return pub

    def publish_grid(self, topic: str, grid: OccupancyGridFields, *,
                     force: bool = False) -> bool:
        """Publish ``grid`` on ``topic`` unless it equals the last one there (or ``force``)."""
        digest = _digest(grid)
        with self._lock:
            if self._closed:
                return False
            pub = self._publisher(topic)
            if digest == pub.digest and not force:
                return False
            payload = cdr.encode_occupancy_grid(grid)
            pub.seq += 1
            pub.publisher.put(payload, attachment=encode_attachment(pub.seq, _now_ns(), pub.gid))
            pub.digest = digest
        self._count("grids_published")
        return True

    def publish_maps(self) -> int:
        """Ask ``map_source`` and publish what changed; returns how many grids were sent."""
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
        return sent

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
