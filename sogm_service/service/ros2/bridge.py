"""ROS 2 robots and tools on the map server, over rmw_zenoh's wire (no ROS install).

The bridge is the Zenoh side of :mod:`sogm_service.adapters.ros2`; it knows nothing of the
server and talks to it through callbacks:

* ISMs: ``nav_msgs/msg/OccupancyGrid`` on every topic under ``ism_prefix``
  (``<domain>/ism/**/nav_msgs::msg::dds_::OccupancyGrid_/*``).  The key's type and hash are
  checked (Jazzy/Kilted/Rolling's RIHS01 hash; Humble's ``TypeHashNotSupported`` only with
  ``humble``), then the attachment (current or keyed form), then the CDR; the grid becomes an
  :class:`~sogm_service.wire.messages.IsmMessage` handed to ``on_ism(key, layer, msg)`` with
  layer and robot from the topic.  Every refusal goes to ``on_reject(what, code, text)``
  (``what``: ``ism``, ``pose``, ``tf`` or ``get_map``) and is counted per code; nothing is
  fused from a refused sample.
* Poses: PoseStamped on ``/{robot}/pose``, Odometry on ``/{robot}/odom`` and TFMessage on
  ``/tf`` + ``/tf_static`` (the chain ``map_frame`` -> ``robot_frame``), each to
  ``on_pose(robot, x, y, yaw, stamp)``.
* Maps out: :meth:`Ros2Bridge.publish_maps` asks ``map_source()`` for a
  :class:`~sogm_service.adapters.ros2.views.MapSnapshot` (layer grids and the fused grid, as
  :func:`~sogm_service.adapters.ros2.views.map_snapshot` makes them) and publishes each grid
  that changed on ``/sogm/<map>/layers/<layer>`` and ``/sogm/<map>/map``, TRANSIENT_LOCAL
  depth 1: a Zenoh advanced publisher with a cache of one sample, publisher detection and a
  sporadic heartbeat, so a late RViz or nav2 (advanced subscriber with history and
  late-publisher detection, as rmw_zenoh declares them) still gets the map.  Congestion
  control is BLOCK (rmw_zenoh uses DROP for KEEP_LAST): maps are megabytes, are only sent when
  they change, and a dropped one would not come again until the next change.
  Attachments carry a sequence number from 1 per publisher, the time and the publisher's gid.
* ``nav_msgs/srv/GetMap`` on ``/sogm/<map>/get_map``: a complete queryable; the reply carries
  the CDR response and an attachment echoing the request's sequence number and client gid.
* Liveliness tokens for the node and each endpoint, so ``ros2 node list`` / ``ros2 topic
  list`` show the server.  Subscriptions to wildcards have no ROS topic name, so a
  subscription token is declared per concrete topic, as it is seen (a publisher's token, or
  its first sample), up to ``max_topics``.

Threads: the callbacks run on Zenoh's callback threads; decoding an OccupancyGrid is a copy
of its cells plus validation, so it is done there.  ``on_ism`` should only enqueue.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

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
from sogm_service.adapters.ros2.convert import (
    DEFAULT_MAX_TILT,
    RobotPose,
    TfTree,
    grid_to_ism,
    pose_to_robot,
)
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import (
    GET_MAP,
    HUMBLE_HASH,
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_STAMPED,
    QOS_DEFAULT,
    QOS_LATCHED,
    QOS_SERVICES,
    TF_MESSAGE,
    EntityKind,
    Qos,
    check_type,
    entity_token,
    node_token,
    parse_data_key,
    parse_token,
    pattern_key,
    robot_from_topic,
    ros_safe_name,
    ros_type_name,
    service_key,
    strip_name,
    subscription_key,
    topic_key,
    topic_layer,
    type_hash,
)
from sogm_service.adapters.ros2.views import MapSnapshot
from sogm_service.wire.limits import MAX_ISM_CELLS, MAX_PAYLOAD_BYTES
from sogm_service.wire.messages import IsmMessage

log = logging.getLogger("sogm_service.service.ros2.bridge")

OnIsm = Callable[[str, str, IsmMessage], None]
OnPose = Callable[[str, float, float, float, float], None]
OnReject = Callable[[str, str, str], None]  # (what, code, text)
MapSource = Callable[[], MapSnapshot]

QOS_TF = Qos(depth=100)
HEARTBEAT_PERIOD_S = 1.0
"""rmw_zenoh's RELIABLE + TRANSIENT_LOCAL publishers send a sporadic heartbeat (sequence-number
sequencing, so no Zenoh ``timestamping`` is needed) for subscribers to recover a missed last
sample from the cache."""
QOS_TF_STATIC = Qos(durability=QOS_LATCHED.durability, depth=1)


@dataclass(frozen=True)
class Ros2BridgeSettings:
    """What the ``[ros2]`` config section would hold (see NOTES-ros2.md)."""

    domain: int = 0
    ism_prefix: str = "/ism"
    pose_topics: tuple[str, ...] = ("/{robot}/pose",)
    odom_topics: tuple[str, ...] = ("/{robot}/odom",)
    tf_topics: tuple[str, ...] = ("/tf",)
    tf_static_topics: tuple[str, ...] = ("/tf_static",)
    map_frame: str = "map"
    robot_frame: str = "{robot}/base_link"
    humble: bool = False
    topic_root: str = "/sogm"
    node_name: str = "sogm_service"
    namespace: str = "/"
    max_payload_bytes: int = MAX_PAYLOAD_BYTES
    max_cells: int = MAX_ISM_CELLS
    max_tilt: float = DEFAULT_MAX_TILT
    max_topics: int = 4096
    max_frames: int = 1024


@dataclass
class _Publisher:
    topic: str
    key: str
    publisher: Any  # zenoh.ext.AdvancedPublisher
    token: Any
    gid: bytes
    seq: int = 0
    digest: bytes = b""


def _now_ns() -> int:
    return time.time_ns()


def _digest(g: OccupancyGridFields) -> bytes:
    """What makes a grid "changed": cells, geometry and frame (not the stamp)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((g.frame, g.resolution, g.width, g.height, g.position,
                   g.orientation)).encode())
    h.update(g.data.tobytes())
    return h.digest()


class Ros2Bridge:
    """Subscriptions, publishers, tokens and the GetMap service of one map over rmw_zenoh."""

    def __init__(self, session: zenoh.Session, *, map_name: str,
                 settings: Ros2BridgeSettings | None = None,
                 on_ism: OnIsm | None = None, on_pose: OnPose | None = None,
                 on_reject: OnReject | None = None,
                 map_source: MapSource | None = None) -> None:
        self.session = session
        self.settings = s = settings or Ros2BridgeSettings()
        self.map_name = map_name
        self._on_ism = on_ism
        self._on_pose = on_pose
        self._on_reject = on_reject
        self._map_source = map_source
        self.zid = str(session.info.zid())
        self._ids = itertools.count(1)
        self.node_id = 0
        self._lock = threading.RLock()
        self._tf_lock = threading.Lock()
        self._tf = TfTree(s.map_frame, s.robot_frame, s.max_frames)
        self.counters: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self._publishers: dict[str, _Publisher] = {}
        self._sub_tokens: dict[tuple[str, str], Any] = {}
        self._declared: list[Any] = []
        self._tokens: dict[str, Any] = {}
        self._last_fused: OccupancyGridFields | None = None
        self._closed = False
        root = "/" + strip_name(s.topic_root) if strip_name(s.topic_root) else ""
        self.base_topic = f"{root}/{ros_safe_name(map_name)}"
        self.map_topic = f"{self.base_topic}/map"
        self.get_map_service = f"{self.base_topic}/get_map"
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    # -- declarations ---------------------------------------------------------------------
    def _token(self, key: str) -> Any:
        tok = self.session.liveliness().declare_token(key)
        self._tokens[key] = tok
        return tok

    def _entity_token(self, kind: str, topic: str, ros_type: str, qos: Qos) -> str:
        s = self.settings
        key = entity_token(s.domain, self.zid, self.node_id, next(self._ids), kind,
                           s.node_name, topic, ros_type, qos.key(), namespace=s.namespace,
                           hash_=type_hash(ros_type))
        self._token(key)
        return key

    def _declare(self) -> None:
        s, z = self.settings, self.session
        self.node_token = node_token(s.domain, self.zid, self.node_id, s.node_name,
                                     s.namespace)
        self._token(self.node_token)
        self._declared.append(z.declare_subscriber(
            subscription_key(s.domain, s.ism_prefix, OCCUPANCY_GRID), self._on_ism_sample))
        for pattern in s.pose_topics:
            self._declared.append(z.declare_subscriber(
                pattern_key(s.domain, pattern, POSE_STAMPED),
                self._pose_callback(pattern, POSE_STAMPED)))
        for pattern in s.odom_topics:
            self._declared.append(z.declare_subscriber(
                pattern_key(s.domain, pattern, ODOMETRY), self._pose_callback(pattern, ODOMETRY)))
        for topic in s.tf_topics:
            self._declared.append(z.declare_subscriber(
                topic_key(s.domain, topic, TF_MESSAGE, "*"), self._tf_callback(False)))
            self._entity_token(EntityKind.SUBSCRIPTION, topic, TF_MESSAGE, QOS_TF)
        for topic in s.tf_static_topics:  # latched: a late joiner asks the cache
            self._declared.append(zenoh.ext.declare_advanced_subscriber(
                z, topic_key(s.domain, topic, TF_MESSAGE, "*"), self._tf_callback(True),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True)))
            self._entity_token(EntityKind.SUBSCRIPTION, topic, TF_MESSAGE, QOS_TF_STATIC)
        hashes = [type_hash(GET_MAP)] + ([HUMBLE_HASH] if s.humble else [])
        for h in hashes:
            self._declared.append(z.declare_queryable(
                service_key(s.domain, self.get_map_service, GET_MAP, h), self._on_get_map,
                complete=True))
        self.get_map_token = self._entity_token(EntityKind.SERVICE_SERVER,
                                                self.get_map_service, GET_MAP, QOS_SERVICES)
        # Subscription tokens for the publishers we would receive from, as they appear.
        self._declared.append(z.liveliness().declare_subscriber(
            f"@ros2_lv/{int(s.domain)}/**", self._on_liveliness, history=True))

    def token_keys(self) -> list[str]:
        """Every liveliness token this bridge has declared."""
        with self._lock:
            return list(self._tokens)

    # -- bookkeeping ----------------------------------------------------------------------
    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def _reject(self, what: str, code: str, text: str) -> None:
        with self._lock:
            self.rejected[code] += 1
        log.debug("ROS 2 input refused [%s]: %s", code, text)
        if self._on_reject is not None:
            try:
                self._on_reject(what, code, text)
            except Exception:
                log.exception("on_reject failed")

    def stats(self) -> dict[str, Any]:
        """Counters and refusals by code (for the server's stats reply)."""
        with self._lock:
            return {"counters": dict(self.counters), "rejected": dict(self.rejected),
                    "publishers": len(self._publishers),
                    "subscription_tokens": len(self._sub_tokens)}

    def _ensure_subscription_token(self, topic: str, ros_type: str) -> None:
        qos = QOS_DEFAULT
        with self._lock:
            if self._closed or (topic, ros_type) in self._sub_tokens:
                return
            if len(self._sub_tokens) >= self.settings.max_topics:
                return
            self._sub_tokens[(topic, ros_type)] = True
            self._entity_token(EntityKind.SUBSCRIPTION, topic, ros_type, qos)

    def _wanted(self, topic: str, ros_type: str) -> bool:
        s = self.settings
        if ros_type == OCCUPANCY_GRID:
            try:
                topic_layer(topic, s.ism_prefix)
                return True
            except Ros2DecodeError:
                return False
        patterns = s.pose_topics if ros_type == POSE_STAMPED else \
            s.odom_topics if ros_type == ODOMETRY else ()
        return any(robot_from_topic(p, topic) for p in patterns)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            tok = parse_token(str(sample.key_expr))
        except Ros2DecodeError:
            return
        if tok.kind != EntityKind.PUBLISHER or tok.zid == self.zid:
            return
        try:
            ros_type = ros_type_name(tok.dds_type)
        except Ros2DecodeError:
            return
        if ros_type in (OCCUPANCY_GRID, POSE_STAMPED, ODOMETRY) and \
                self._wanted(tok.topic, ros_type):
            self._ensure_subscription_token(tok.topic, ros_type)

    # -- incoming samples -----------------------------------------------------------------
    def _check_sample(self, sample: zenoh.Sample, ros_type: str) -> tuple[str, bytes]:
        """Key, type, size and attachment of a sample; its topic and payload."""
        s = self.settings
        dk = parse_data_key(str(sample.key_expr))
        check_type(dk, ros_type, s.humble)
        size = len(sample.payload)
        if size > s.max_payload_bytes:
            raise Ros2DecodeError("too_large", f"payload of {size} bytes exceeds "
                                               f"{s.max_payload_bytes}")
        att = sample.attachment
        parse_attachment(att.to_bytes() if att is not None else None)
        return dk.topic, sample.payload.to_bytes()

    def _on_ism_sample(self, sample: zenoh.Sample) -> None:
        self._count("isms_received")
        key = str(sample.key_expr)
        s = self.settings
        try:
            topic, payload = self._check_sample(sample, OCCUPANCY_GRID)
            layer, robot = topic_layer(topic, s.ism_prefix)
            grid = cdr.decode_occupancy_grid(payload, max_bytes=s.max_payload_bytes,
                                             max_cells=s.max_cells)
            msg = grid_to_ism(grid, layer=layer, robot=robot, max_tilt=s.max_tilt,
                              max_cells=s.max_cells)
        except Ros2DecodeError as exc:
            self._reject("ism", exc.code, f"{key}: {exc.message}")
            return
        self._ensure_subscription_token(topic, OCCUPANCY_GRID)
        self._count("isms_accepted")
        if self._on_ism is not None:
            try:
                self._on_ism(key, layer, msg)
            except Exception:
                log.exception("on_ism failed for %s", key)

    def _emit_pose(self, p: RobotPose) -> None:
        self._count("poses_accepted")
        if self._on_pose is not None:
            try:
                self._on_pose(p.robot, p.x, p.y, p.yaw, p.stamp)
            except Exception:
                log.exception("on_pose failed for %s", p.robot)

    def _pose_callback(self, pattern: str, ros_type: str) -> Callable[[zenoh.Sample], None]:
        decode = cdr.decode_pose_stamped if ros_type == POSE_STAMPED else cdr.decode_odometry

        def on_sample(sample: zenoh.Sample) -> None:
            self._count("poses_received")
            key = str(sample.key_expr)
            try:
                topic, payload = self._check_sample(sample, ros_type)
                robot = robot_from_topic(pattern, topic)
                if not robot:
                    raise Ros2DecodeError("bad_key", f"{topic} does not match {pattern}")
                pose = pose_to_robot(decode(payload), robot, self.settings.map_frame)
            except Ros2DecodeError as exc:
                self._reject("pose", exc.code, f"{key}: {exc.message}")
                return
            self._ensure_subscription_token(topic, ros_type)
            self._emit_pose(pose)
        return on_sample

    def _tf_callback(self, static: bool) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            self._count("tf_received")
            key = str(sample.key_expr)
            try:
                _, payload = self._check_sample(sample, TF_MESSAGE)
                transforms = cdr.decode_tf_message(payload)
                with self._tf_lock:
                    poses = self._tf.update(transforms, static=static)
            except Ros2DecodeError as exc:
                self._reject("tf", exc.code, f"{key}: {exc.message}")
                return
            for p in poses:
                self._emit_pose(p)
        return on_sample

    # -- maps out -------------------------------------------------------------------------
    def layer_topic(self, layer: str) -> str:
        return f"{self.base_topic}/layers/{ros_safe_name(layer)}"

    def _publisher(self, topic: str) -> _Publisher:
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
            pub = _Publisher(topic, key, publisher, self._tokens[token_key], gid_of(token_key))
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

    # -- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        """Undeclare everything (the session stays open: it is the caller's)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = [*self._declared, *(p.publisher for p in self._publishers.values()),
                        *self._tokens.values()]
            self._declared.clear()
            self._publishers.clear()
            self._tokens.clear()
        for e in reversed(entities):
            try:
                e.undeclare()
            except Exception:  # already gone with a closing session
                log.debug("undeclare failed", exc_info=True)

    def __enter__(self) -> Ros2Bridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _echo_attachment(request: Attachment) -> bytes:
    """A reply's attachment: the request's sequence number and gid, the reply's time."""
    if len(request.gid) == 16:
        return encode_attachment(request.sequence_number, _now_ns(), request.gid)
    # a Humble client's 24-byte gid, echoed as it came
    return struct.pack("<qq", request.sequence_number, _now_ns()) + bytes([len(request.gid)]) \
        + request.gid
