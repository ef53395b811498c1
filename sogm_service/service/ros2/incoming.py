"""What the ROS 2 bridge receives (:class:`Incoming`): ISMs as ``nav_msgs/msg/OccupancyGrid``,
poses as PoseStamped, Odometry and TF, each checked (key, type hash, size, attachment, CDR) and
handed to the server's callbacks; every refusal is counted and reported.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh

from sogm_service.adapters.ros2 import cdr
from sogm_service.adapters.ros2.attachment import parse_attachment
from sogm_service.adapters.ros2.convert import RobotPose, grid_to_ism, pose_to_robot
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import (
    OCCUPANCY_GRID,
    POSE_STAMPED,
    TF_MESSAGE,
    check_type,
    parse_data_key,
    robot_from_topic,
    topic_layer,
)
from sogm_service.service.ros2.state import BridgeState

log = logging.getLogger("sogm_service.service.ros2.bridge")  # one logger for the bridge's parts


class Incoming(BridgeState):
    """The bridge's subscriber callbacks."""

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
