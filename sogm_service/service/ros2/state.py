"""What every part of the ROS 2 bridge shares (:class:`BridgeState`): the session and settings,
the server's callbacks, the liveliness tokens of the node and its endpoints (a subscription token
per concrete topic, as publishers appear), and the counters and refusals of the stats reply.
"""

from __future__ import annotations

import itertools
import logging
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Any

import zenoh

from sogm_service.adapters.ros2.cdr import OccupancyGridFields
from sogm_service.adapters.ros2.convert import TfTree
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.filterinfo import FilterInfoFields
from sogm_service.adapters.ros2.keys import (
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_STAMPED,
    QOS_DEFAULT,
    EntityKind,
    Qos,
    entity_token,
    parse_token,
    robot_from_topic,
    ros_safe_name,
    ros_type_name,
    strip_name,
    topic_layer,
    type_hash,
)
from sogm_service.service.ros2.settings import (
    MapSource,
    OnIsm,
    OnPose,
    OnReject,
    Ros2BridgeSettings,
)

log = logging.getLogger("sogm_service.service.ros2.bridge")  # one logger for the bridge's parts


@dataclass
class Publisher:
    """One topic's advanced publisher, its token and gid, its sequence number; for a map topic
    the last grid sent (what its subscribers hold), when the last whole grid went out and how
    many updates followed it."""

    topic: str
    key: str
    publisher: Any  # zenoh.ext.AdvancedPublisher
    token: Any
    gid: bytes
    seq: int = 0
    last: OccupancyGridFields | None = None
    full_at: float = 0.0  # time.monotonic() of the last whole grid
    updates_since_full: int = 0
    whole_bytes: int = 0  # the last whole grid's payload: what each round of updates saves
    joined: bool = False  # a subscriber appeared since the last whole grid


class BridgeState:
    """The bridge's session, settings, callbacks, tokens and counters."""

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
        self._publishers: dict[str, Publisher] = {}
        self._sub_tokens: dict[tuple[str, str], Any] = {}
        self._declared: list[Any] = []
        self._tokens: dict[str, Any] = {}
        self._last_fused: OccupancyGridFields | None = None
        self._filter_infos: dict[str, FilterInfoFields] = {}  # the last sent, per topic
        self._closed = False
        root = "/" + strip_name(s.topic_root) if strip_name(s.topic_root) else ""
        self.base_topic = f"{root}/{ros_safe_name(map_name)}"
        self.map_topic = f"{self.base_topic}/map"
        self.get_map_service = f"{self.base_topic}/get_map"

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

    def _subscriber_joined(self, topic: str) -> None:
        """A ROS subscriber of one of our map topics appeared: its next publication is a
        whole grid.  A late subscriber gets only the latched grid and the latched last update,
        so without it the updates in between would be missing from its copy."""
        with self._lock:
            pub = self._publishers.get(topic)
            if pub is not None and pub.last is not None:
                pub.joined = True
                self.counters["subscribers_joined"] += 1

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
        if tok.zid == self.zid:
            return
        if tok.kind == EntityKind.SUBSCRIPTION:
            self._subscriber_joined(tok.topic)
            return
        if tok.kind != EntityKind.PUBLISHER:
            return
        try:
            ros_type = ros_type_name(tok.dds_type)
        except Ros2DecodeError:
            return
        if ros_type in (OCCUPANCY_GRID, POSE_STAMPED, ODOMETRY) and \
                self._wanted(tok.topic, ros_type):
            self._ensure_subscription_token(tok.topic, ros_type)
