"""rmw_zenoh key expressions, liveliness tokens, type names and hashes, QoS strings (pure).

The formats are those of rmw_zenoh's upstream releases (Jazzy 0.2.x, Kilted 0.6.x, Rolling
0.12.x; Humble 0.1.x writes ``TypeHashNotSupported`` in place of the hash), as rmw_zenoh's
design document describes them:

* data key of a topic: ``<domain>/<topic without outer '/'>/<dds type name>/<type hash>``;
* service key: the same with the service's type name and hash (not its Request/Response's);
* liveliness tokens under the hermetic chunk ``@ros2_lv`` (``**`` never matches it): one for the
  node (``NN``) and one per publisher (``MP``), subscription (``MS``), service server (``SS``)
  or client (``SC``), names mangled with every ``/`` as ``%``;
* the QoS string of an endpoint token, each field empty when equal to rmw_zenoh's default.

The RIHS01 hashes are literals here (REP-2011: sha256 of the type description); the tests
recompute them with rosbags and check them against the spec's strings.  ``GetMap``'s is the
hash of the service description (request, response and event message), computed by the same
method that reproduces rmw_zenoh's documented ``AddTwoInts`` hash.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import IntEnum

from sogm_service.adapters.ros2.errors import Ros2DecodeError

LIVELINESS_PREFIX = "@ros2_lv"
HUMBLE_HASH = "TypeHashNotSupported"

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
GET_MAP = "nav_msgs/srv/GetMap"
OCCUPANCY_GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
COSTMAP_FILTER_INFO = "nav2_msgs/msg/CostmapFilterInfo"

TYPE_HASHES: dict[str, str] = {
    OCCUPANCY_GRID: "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    POSE_STAMPED: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    ODOMETRY: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    TF_MESSAGE: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    LASER_SCAN: "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
    GET_MAP: "RIHS01_c8ae77c9995b3554b5ba80e4d4d443f970ac65143102a1d893ec24fc07b31147",
    OCCUPANCY_GRID_UPDATE:
        "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8",
    COSTMAP_FILTER_INFO:
        "RIHS01_61ce391bf7690f76a331c01c9d5ce8ca71e6c99273b9fb75e48380f05c6dfdc8",
}
"""REP-2011 type hashes (identical in Jazzy, Kilted and Rolling for these types)."""

_ROS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)$")
_DDS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)::(msg|srv)::dds_::([A-Za-z][A-Za-z0-9_]*)_$")
_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")


def dds_type_name(ros_type: str) -> str:
    """``nav_msgs/msg/OccupancyGrid`` -> ``nav_msgs::msg::dds_::OccupancyGrid_``."""
    m = _ROS_TYPE.match(ros_type)
    if not m:
        raise ValueError(f"not a ROS 2 type name: {ros_type!r}")
    return f"{m[1]}::{m[2]}::dds_::{m[3]}_"


def ros_type_name(dds_type: str) -> str:
    """``nav_msgs::msg::dds_::OccupancyGrid_`` -> ``nav_msgs/msg/OccupancyGrid``."""
    m = _DDS_TYPE.match(dds_type)
    if not m:
        raise Ros2DecodeError("bad_key", f"not an rmw_zenoh type name: {dds_type!r}")
    return f"{m[1]}/{m[2]}/{m[3]}"


def type_hash(ros_type: str, humble: bool = False) -> str:
    """The key's hash chunk of a type (``TypeHashNotSupported`` for Humble)."""
    return HUMBLE_HASH if humble else TYPE_HASHES[ros_type]


def strip_name(name: str) -> str:
    """A ROS name without its outer ``/`` (the key-expression form)."""
    return name.strip("/")


def mangle(name: str) -> str:
    """Liveliness form of a name: every ``/`` becomes ``%`` (``/`` alone, or empty, is ``%``)."""
    return name.replace("/", "%") if name and name != "/" else "%"


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


_ROS_TOKEN_BAD = re.compile(r"[^A-Za-z0-9_]")


def ros_safe_name(name: str) -> str:
    """A layer or map name made into valid ROS name tokens (``/``-separated).

    Characters outside ``[A-Za-z0-9_]`` become ``_`` and a token that starts with a digit gets a
    leading ``_`` (``robot1/2d-obstacle`` -> ``robot1/_2d_obstacle``).  A class pattern's glob
    characters are spelled out: ``*`` is ``all`` and ``?`` is ``any`` (``*/laser/obstacle`` ->
    ``all/laser/obstacle``, ``robot*/person`` -> ``robotall/person``).
    """
    tokens = []
    for tok in name.strip("/").split("/"):
        tok = tok.replace("*", "all").replace("?", "any")
        if not tok:
            continue
        tok = _ROS_TOKEN_BAD.sub("_", tok)
        tokens.append("_" + tok if tok[0].isdigit() else tok)
    return "/".join(tokens)


def topic_key(domain: int, topic: str, ros_type: str, hash_: str | None = None) -> str:
    """Data key of a topic (or service): ``0/ism/robot1/obstacle/nav_msgs::msg::dds_::...``."""
    h = hash_ if hash_ is not None else TYPE_HASHES[ros_type]
    return f"{int(domain)}/{strip_name(topic)}/{dds_type_name(ros_type)}/{h}"


def service_key(domain: int, service: str, srv_type: str = GET_MAP,
                hash_: str | None = None) -> str:
    """Key of a service (its queryable and the clients' ``get``)."""
    return topic_key(domain, service, srv_type, hash_)


def subscription_key(domain: int, prefix: str, ros_type: str, hash_: str = "*") -> str:
    """Every topic under ``prefix`` of one type: ``0/ism/**/nav_msgs::msg::dds_::OccupancyGrid_/*``.

    ``**`` also matches zero chunks, so a topic equal to the prefix's child (``/ism/obstacle``)
    is included; it never matches the hermetic ``@adv`` chunks of advanced publishers.
    """
    p = strip_name(prefix)
    middle = f"{p}/**" if p else "**"
    return f"{int(domain)}/{middle}/{dds_type_name(ros_type)}/{hash_}"


def pattern_key(domain: int, pattern: str, ros_type: str, hash_: str = "*") -> str:
    """Key of a topic pattern with a ``{robot}`` chunk: ``/{robot}/pose`` -> ``0/*/pose/...``."""
    p = strip_name(pattern).replace("{robot}", "*")
    return f"{int(domain)}/{p}/{dds_type_name(ros_type)}/{hash_}"


def robot_from_topic(pattern: str, topic: str) -> str | None:
    """The ``{robot}`` chunk of ``topic`` under ``pattern`` (None if it does not match)."""
    pat = strip_name(pattern).split("/")
    got = strip_name(topic).split("/")
    if len(pat) != len(got):
        return None
    robot: str | None = None
    for p, g in zip(pat, got, strict=True):
        if p == "{robot}":
            robot = g
        elif p not in ("*", g):
            return None
    return robot


@dataclass(frozen=True, slots=True)
class DataKey:
    """A received data key, parsed back."""

    domain: int
    topic: str  # fully qualified, with the leading '/'
    dds_type: str
    type_hash: str

    @property
    def ros_type(self) -> str:
        return ros_type_name(self.dds_type)

    @property
    def humble(self) -> bool:
        return self.type_hash == HUMBLE_HASH


def parse_data_key(key: str) -> DataKey:
    """``0/ism/robot1/obstacle/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_...`` -> parts."""
    chunks = str(key).split("/")
    if len(chunks) < 4:
        raise Ros2DecodeError("bad_key", f"{key!r} has fewer than 4 chunks")
    domain_s, *topic, dds_type, hash_ = chunks
    if not domain_s.isdigit() or len(domain_s) > 3:
        raise Ros2DecodeError("bad_key", f"{key!r} does not start with a domain id")
    if not (_HASH.match(hash_) or hash_ == HUMBLE_HASH):
        raise Ros2DecodeError("bad_key", f"{key!r} does not end with a type hash")
    if not _DDS_TYPE.match(dds_type):
        raise Ros2DecodeError("bad_key", f"{key!r} has no rmw_zenoh type name")
    return DataKey(int(domain_s), "/" + "/".join(topic), dds_type, hash_)


def check_type(dk: DataKey, ros_type: str, humble: bool) -> None:
    """Refuse a key of another type, of an unknown hash, or of Humble when not enabled."""
    if dk.dds_type != dds_type_name(ros_type):
        raise Ros2DecodeError("wrong_type", f"{dk.topic}: type {dk.dds_type}, not {ros_type}")
    if dk.humble:
        if not humble:
            raise Ros2DecodeError("humble_disabled",
                                  f"{dk.topic}: Humble sample and [ros2] humble is off")
        return
    if dk.type_hash != TYPE_HASHES[ros_type]:
        raise Ros2DecodeError("type_hash", f"{dk.topic}: type hash {dk.type_hash} is not "
                                           f"{TYPE_HASHES[ros_type]} ({ros_type})")


_LAYER_NAME = re.compile(r"^[A-Za-z0-9_\-./]{1,128}$")


def topic_layer(topic: str, prefix: str = "/ism") -> tuple[str, str | None]:
    """Layer and robot of an ISM topic, as for native keys.

    ``/ism/robot1/obstacle`` -> (``robot1/obstacle``, ``robot1``); a single chunk under the
    prefix (``/ism/obstacle``) has no robot.
    """
    p = strip_name(prefix)
    t = strip_name(topic)
    if p:
        if not t.startswith(p + "/"):
            raise Ros2DecodeError("bad_layer", f"topic {topic!r} is not under {prefix!r}")
        t = t[len(p) + 1:]
    if not _LAYER_NAME.match(t) or any(not c for c in t.split("/")):
        raise Ros2DecodeError("bad_layer", f"topic {topic!r} gives no valid layer name")
    parts = t.split("/")
    return t, (parts[0] if len(parts) > 1 else None)


class EntityKind:
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE_SERVER = "SS"
    SERVICE_CLIENT = "SC"


def node_token(domain: int, zid: str, node_id: int, node_name: str, namespace: str = "/",
               enclave: str = "/") -> str:
    """``@ros2_lv/<domain>/<zid>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>``."""
    return "/".join([LIVELINESS_PREFIX, str(int(domain)), zid, str(node_id), str(node_id),
                     EntityKind.NODE, mangle(enclave), mangle(namespace), node_name])


def entity_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str,
                 node_name: str, topic: str, ros_type: str, qos: str, *,
                 namespace: str = "/", enclave: str = "/", hash_: str | None = None) -> str:
    """Liveliness token of a publisher/subscription/service server or client."""
    h = hash_ if hash_ is not None else TYPE_HASHES[ros_type]
    return "/".join([LIVELINESS_PREFIX, str(int(domain)), zid, str(node_id), str(entity_id),
                     kind, mangle(enclave), mangle(namespace), node_name,
                     mangle("/" + strip_name(topic)), dds_type_name(ros_type), h, qos])


@dataclass(frozen=True, slots=True)
class Token:
    """A parsed liveliness token (endpoint fields empty for a node token)."""

    domain: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str = ""
    dds_type: str = ""
    type_hash: str = ""
    qos: str = ""


def parse_token(key: str) -> Token:
    """Parse a ``@ros2_lv/...`` key (node or endpoint); ``Ros2DecodeError('bad_key')`` if not."""
    c = str(key).split("/")
    try:
        if c[0] != LIVELINESS_PREFIX:
            raise ValueError("not under @ros2_lv")
        base = dict(domain=int(c[1]), zid=c[2], node_id=int(c[3]), entity_id=int(c[4]),
                    kind=c[5], enclave=demangle(c[6]), namespace=demangle(c[7]),
                    node_name=c[8])
        if c[5] == EntityKind.NODE and len(c) == 9:
            return Token(**base)  # type: ignore[arg-type]
        if c[5] in ("MP", "MS", "SS", "SC") and len(c) == 13:
            return Token(**base, topic=demangle(c[9]), dds_type=c[10],  # type: ignore[arg-type]
                         type_hash=c[11], qos=c[12])
        raise ValueError(f"kind {c[5]!r} with {len(c)} chunks")
    except (IndexError, ValueError) as exc:
        raise Ros2DecodeError("bad_key", f"{key!r} is not an rmw_zenoh token: {exc}") from None


class Reliability(IntEnum):
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(IntEnum):
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(IntEnum):
    KEEP_LAST = 1
    KEEP_ALL = 2


DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth (left empty in the string)


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS of an endpoint; durations in (s, ns), ``None`` for infinite."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] | None = None
    lifespan: tuple[int, int] | None = None
    liveliness_manual: bool = False
    lease: tuple[int, int] | None = None

    def key(self) -> str:
        """The token's QoS chunk, e.g. ``::,10:,:,:,,`` (rclcpp default)."""
        def dur(d: tuple[int, int] | None) -> str:
            return "," if d is None else f"{d[0]},{d[1]}"
        rel = "" if self.reliability == Reliability.RELIABLE else str(int(self.reliability))
        durab = "" if self.durability == Durability.VOLATILE else str(int(self.durability))
        hist = "" if self.history == History.KEEP_LAST else str(int(self.history))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        live = "3" if self.liveliness_manual else ""  # RMW_QOS_POLICY_LIVELINESS_MANUAL_BY_TOPIC
        return f"{rel}:{durab}:{hist},{depth}:{dur(self.deadline)}:{dur(self.lifespan)}:" \
               f"{live},{dur(self.lease)}"


QOS_DEFAULT = Qos()  # rclcpp's default (depth 10): ``::,10:,:,:,,``
QOS_LATCHED = Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)  # nav2 /map: ``:1:,1:,:,:,,``
QOS_SERVICES = Qos()  # rmw_qos_profile_services_default: reliable, volatile, depth 10
