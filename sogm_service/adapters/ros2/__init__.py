"""ROS 2 over rmw_zenoh's wire, without ROS: pure codecs and key formats (no zenoh import).

* :mod:`.keys`: data keys, service keys, liveliness tokens, type names and hashes, QoS strings;
* :mod:`.attachment`: the per-sample attachment (sequence, timestamp, gid);
* :mod:`.cdr`: CDR of OccupancyGrid, PoseStamped, Odometry, TFMessage, LaserScan, GetMap
  through rosbags;
* :mod:`.convert`: OccupancyGrid <-> ISM, map window -> OccupancyGrid, poses and TF chains.

The Zenoh side (subscriptions, advanced publishers, tokens, the GetMap queryable) is
:mod:`sogm_service.service.ros2.bridge`.
"""

from sogm_service.adapters.ros2.errors import REJECT_CODES, Ros2DecodeError

__all__ = ["REJECT_CODES", "Ros2DecodeError"]
