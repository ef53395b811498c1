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
  :func:`~sogm_service.adapters.ros2.views.map_snapshot` makes them) and publishes what
  changed of each on ``/sogm/<map>/layers/<layer>`` and ``/sogm/<map>/map`` (whole grids) or
  on ``<topic>_updates`` (``map_msgs/msg/OccupancyGridUpdate`` rectangles,
  :mod:`~sogm_service.service.ros2.mapsout`), all TRANSIENT_LOCAL depth 1: a Zenoh advanced
  publisher with a cache of one sample, publisher detection and a sporadic heartbeat, so a
  late RViz or nav2 (advanced subscriber with history and late-publisher detection, as
  rmw_zenoh declares them) still gets the map.  Congestion control is BLOCK (rmw_zenoh uses
  DROP for KEEP_LAST): maps are megabytes, are only sent when they change, and a dropped one
  would not come again until the next change.
  Attachments carry a sequence number from 1 per publisher, the time and the publisher's gid.
* nav2's filter masks (the snapshot's ``masks``, :mod:`sogm_service.adapters.ros2.filters`):
  ``/sogm/<map>/keepout_mask`` and ``speed_mask`` through the same path (whole at every change
  with ``whole_masks``, else with ``_updates``), each with its latched
  ``nav2_msgs/msg/CostmapFilterInfo`` on ``<mask>_filter_info``, sent again only if it changes.
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

import logging

import zenoh
import zenoh.ext

from sogm_service.adapters.ros2.keys import (
    GET_MAP,
    HUMBLE_HASH,
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_STAMPED,
    QOS_LATCHED,
    QOS_SERVICES,
    TF_MESSAGE,
    EntityKind,
    Qos,
    node_token,
    pattern_key,
    service_key,
    subscription_key,
    topic_key,
    type_hash,
)
from sogm_service.service.ros2.incoming import Incoming
from sogm_service.service.ros2.mapsout import MapsOut
from sogm_service.service.ros2.settings import (
    MapSource,
    OnIsm,
    OnPose,
    OnReject,
    Ros2BridgeSettings,
)

log = logging.getLogger("sogm_service.service.ros2.bridge")  # one logger for the bridge's parts

QOS_TF = Qos(depth=100)
QOS_TF_STATIC = Qos(durability=QOS_LATCHED.durability, depth=1)


class Ros2Bridge(Incoming, MapsOut):
    """Subscriptions, publishers, tokens and the GetMap service of one map over rmw_zenoh: the
    shared state (:class:`~sogm_service.service.ros2.state.BridgeState`), what comes in
    (:class:`~sogm_service.service.ros2.incoming.Incoming`) and what goes out
    (:class:`~sogm_service.service.ros2.mapsout.MapsOut`), declared here."""

    def __init__(self, session: zenoh.Session, *, map_name: str,
                 settings: Ros2BridgeSettings | None = None,
                 on_ism: OnIsm | None = None, on_pose: OnPose | None = None,
                 on_reject: OnReject | None = None,
                 map_source: MapSource | None = None) -> None:
        super().__init__(session, map_name=map_name, settings=settings, on_ism=on_ism,
                         on_pose=on_pose, on_reject=on_reject, map_source=map_source)
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    # -- declarations ---------------------------------------------------------------------
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
