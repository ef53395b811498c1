"""The ROS 2 bridge's settings (:class:`Ros2BridgeSettings`) and the callbacks through which it
hands the server what it receives and asks it for the maps it publishes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from sogm_service.adapters.ros2.convert import DEFAULT_MAX_TILT
from sogm_service.adapters.ros2.views import MapSnapshot
from sogm_service.wire.limits import MAX_ISM_CELLS, MAX_PAYLOAD_BYTES
from sogm_service.wire.messages import IsmMessage

OnIsm = Callable[[str, str, IsmMessage], None]
OnPose = Callable[[str, float, float, float, float], None]
OnReject = Callable[[str, str, str], None]  # (what, code, text)
MapSource = Callable[[], MapSnapshot]


@dataclass(frozen=True)
class Ros2BridgeSettings:
    """The bridge's domain, topics, frames, node name and limits (the server fills it from its
    ``[ros2]`` section, :mod:`sogm_service.service.ros2.link`)."""

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
    full_period_s: float = 300.0  # a whole grid at least this often after updates; 0: never
    whole_masks: bool = True  # nav2's filter masks whole at every change (no updates)
    max_frames: int = 1024
