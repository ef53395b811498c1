"""CDR of the ROS 2 messages the server reads and writes, through rosbags (pure, no zenoh).

Payloads are XCDR1 little-endian with the 4-byte encapsulation header ``00 01 00 00``, as
rmw_zenoh puts them on Zenoh; :mod:`rosbags` (typestore ``ROS2_JAZZY``, the same definitions
for Kilted and Rolling for these types) reads and writes them.  Decoded messages come back as
plain frozen dataclasses of this module, so nothing above depends on rosbags' classes.

Every decoder raises :class:`~sogm_service.adapters.ros2.errors.Ros2DecodeError` only:
``too_large`` (payload above the limit, checked before any work), ``bad_cdr`` (rosbags could
not read it: truncated, a length past the end, an invalid encapsulation), ``non_finite``,
``data_length`` (a grid whose data is not width x height) and ``too_large`` (cells above the
limit).  rosbags reads arrays as views of the payload and checks every length against the
buffer first, so a hostile length never allocates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import (
    GET_MAP,
    LASER_SCAN,
    OCCUPANCY_GRID,
    OCCUPANCY_GRID_UPDATE,
    ODOMETRY,
    POSE_STAMPED,
    TF_MESSAGE,
)

GET_MAP_REQUEST = GET_MAP + "_Request"
GET_MAP_RESPONSE = GET_MAP + "_Response"
CDR_LE_HEADER = b"\x00\x01\x00\x00"

DEFAULT_MAX_PAYLOAD = 128 * 1024 * 1024
DEFAULT_MAX_CELLS = 4096 * 4096
MAX_TRANSFORMS = 1024  # per TFMessage

OCCUPANCY_GRID_UPDATE_MSG = """std_msgs/Header header
int32 x
int32 y
uint32 width
uint32 height
int8[] data
"""
"""``map_msgs/msg/OccupancyGridUpdate``'s definition (rosbags' Jazzy store has no map_msgs):
a rectangle of a grid, ``data`` row-major from cell ``(x, y)``, as nav2's static layer and
RViz's Map display read it on ``<map topic>_updates``."""


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """rosbags' ROS 2 Jazzy typestore, plus ``nav_msgs/srv/GetMap``'s request and response."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register({
        GET_MAP_REQUEST: ([], [("structure_needs_at_least_one_member",
                                (Nodetype.BASE, ("uint8", 0)))]),
        GET_MAP_RESPONSE: ([], [("map", (Nodetype.NAME, OCCUPANCY_GRID))]),
    })
    ts.register(get_types_from_msg(OCCUPANCY_GRID_UPDATE_MSG, OCCUPANCY_GRID_UPDATE))
    return ts


Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]  # x, y, z, w


@dataclass(frozen=True)
class OccupancyGridFields:
    """A nav_msgs/msg/OccupancyGrid, flat.  ``data`` is ``(height, width)`` int8, row 0 first."""

    frame: str
    stamp: float
    resolution: float  # as received (a float32 value: 0.05 arrives as 0.0500000007)
    width: int
    height: int
    position: Vec3
    orientation: Quat
    data: npt.NDArray[np.int8] = field(repr=False)
    map_load_time: float = 0.0


@dataclass(frozen=True)
class GridUpdateFields:
    """A map_msgs/msg/OccupancyGridUpdate, flat: the cells ``data`` (``(height, width)`` int8)
    replace those of the grid from column ``x``, row ``y``."""

    frame: str
    stamp: float
    x: int
    y: int
    width: int
    height: int
    data: npt.NDArray[np.int8] = field(repr=False)


@dataclass(frozen=True)
class PoseFields:
    """A pose with its header: PoseStamped, or Odometry's ``pose.pose`` (``child`` set)."""

    frame: str
    stamp: float
    position: Vec3
    orientation: Quat
    child: str | None = None


@dataclass(frozen=True)
class TransformFields:
    """One geometry_msgs/msg/TransformStamped: ``child`` in ``parent``'s frame."""

    parent: str
    child: str
    stamp: float
    translation: Vec3
    rotation: Quat


@dataclass(frozen=True)
class LaserScanFields:
    frame: str
    stamp: float
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: npt.NDArray[np.float32] = field(repr=False)


def _stamp(t: Any) -> float:
    return float(t.sec) + float(t.nanosec) * 1e-9


def _time(stamp: float) -> Any:
    T = typestore().types["builtin_interfaces/msg/Time"]
    sec = math.floor(stamp)
    nsec = min(round((stamp - sec) * 1e9), 999_999_999)
    return T(sec=int(sec), nanosec=int(nsec))


def _header(frame: str, stamp: float) -> Any:
    H = typestore().types["std_msgs/msg/Header"]
    return H(stamp=_time(stamp), frame_id=frame)


def _vec(v: Any) -> Vec3:
    return (float(v.x), float(v.y), float(v.z))


def _quat(q: Any) -> Quat:
    return (float(q.x), float(q.y), float(q.z), float(q.w))


def _finite(what: str, *values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise Ros2DecodeError("non_finite", f"{what} holds NaN or infinity")


def _deserialize(payload: bytes | bytearray | memoryview, ros_type: str,
                 max_bytes: int) -> Any:
    if len(payload) > max_bytes:
        raise Ros2DecodeError("too_large", f"{ros_type} payload of {len(payload)} bytes "
                                           f"exceeds {max_bytes}")
    try:
        return typestore().deserialize_cdr(bytes(payload), ros_type)
    except Exception as exc:  # rosbags raises SerdeError; be defensive about the rest
        raise Ros2DecodeError("bad_cdr", f"not a CDR {ros_type}: {exc}") from None


def _serialize(msg: Any, ros_type: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, ros_type))


# -- nav_msgs/msg/OccupancyGrid ------------------------------------------------------------
def grid_fields(m: Any, max_cells: int = DEFAULT_MAX_CELLS) -> OccupancyGridFields:
    """A rosbags OccupancyGrid object (decoded here or by a bag reader) -> the flat fields."""
    info = m.info
    width, height = int(info.width), int(info.height)
    res = float(info.resolution)
    pos, ori = _vec(info.origin.position), _quat(info.origin.orientation)
    _finite("the grid origin", *pos, *ori)
    _finite("the grid resolution", res)
    data = _grid_cells(m.data, width, height, max_cells)
    return OccupancyGridFields(
        frame=str(m.header.frame_id), stamp=_stamp(m.header.stamp), resolution=res,
        width=width, height=height, position=pos, orientation=ori,
        data=data.reshape(height, width), map_load_time=_stamp(info.map_load_time))


def decode_occupancy_grid(payload: bytes | bytearray | memoryview, *,
                          max_bytes: int = DEFAULT_MAX_PAYLOAD,
                          max_cells: int = DEFAULT_MAX_CELLS) -> OccupancyGridFields:
    return grid_fields(_deserialize(payload, OCCUPANCY_GRID, max_bytes), max_cells)


def _grid_msg(g: OccupancyGridFields) -> Any:
    T = typestore().types
    data = np.ascontiguousarray(g.data, dtype=np.int8).reshape(-1)
    if data.size != g.width * g.height:
        raise ValueError(f"data has {data.size} cells, {g.width}x{g.height} expected")
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=g.position[0], y=g.position[1],
                                              z=g.position[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=g.orientation[0], y=g.orientation[1],
                                                      z=g.orientation[2], w=g.orientation[3]))
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=_time(g.map_load_time), resolution=float(g.resolution),
        width=int(g.width), height=int(g.height), origin=pose)
    return T[OCCUPANCY_GRID](header=_header(g.frame, g.stamp), info=info, data=data)


def encode_occupancy_grid(g: OccupancyGridFields) -> bytes:
    return _serialize(_grid_msg(g), OCCUPANCY_GRID)


# -- map_msgs/msg/OccupancyGridUpdate -----------------------------------------------------
def encode_grid_update(u: GridUpdateFields) -> bytes:
    T = typestore().types
    data = np.ascontiguousarray(u.data, dtype=np.int8).reshape(-1)
    if data.size != u.width * u.height:
        raise ValueError(f"data has {data.size} cells, {u.width}x{u.height} expected")
    return _serialize(T[OCCUPANCY_GRID_UPDATE](
        header=_header(u.frame, u.stamp), x=int(u.x), y=int(u.y), width=int(u.width),
        height=int(u.height), data=data), OCCUPANCY_GRID_UPDATE)


def _grid_cells(cells: object, width: int, height: int, max_cells: int) -> npt.NDArray[np.int8]:
    """A grid's int8 cells, bounded by ``max_cells`` and checked against its size."""
    if width * height > max_cells:
        raise Ros2DecodeError("too_large", f"{width}x{height} cells exceed the limit of "
                                           f"{max_cells}")
    data = np.asarray(cells, dtype=np.int8)
    if data.size != width * height:
        raise Ros2DecodeError("data_length", f"data has {data.size} cells; {width}x{height} "
                                             f"need {width * height}")
    return data


def decode_grid_update(payload: bytes | bytearray | memoryview, *,
                       max_bytes: int = DEFAULT_MAX_PAYLOAD,
                       max_cells: int = DEFAULT_MAX_CELLS) -> GridUpdateFields:
    m = _deserialize(payload, OCCUPANCY_GRID_UPDATE, max_bytes)
    width, height = int(m.width), int(m.height)
    data = _grid_cells(m.data, width, height, max_cells)
    return GridUpdateFields(str(m.header.frame_id), _stamp(m.header.stamp), int(m.x), int(m.y),
                            width, height, data.reshape(height, width))


# -- poses ---------------------------------------------------------------------------------
def decode_pose_stamped(payload: bytes | bytearray | memoryview, *,
                        max_bytes: int = 1 << 16) -> PoseFields:
    m = _deserialize(payload, POSE_STAMPED, max_bytes)
    pos, ori = _vec(m.pose.position), _quat(m.pose.orientation)
    _finite("the pose", *pos, *ori)
    return PoseFields(str(m.header.frame_id), _stamp(m.header.stamp), pos, ori)


def encode_pose_stamped(p: PoseFields) -> bytes:
    T = typestore().types
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=p.position[0], y=p.position[1], z=p.position[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=p.orientation[0], y=p.orientation[1],
                                                      z=p.orientation[2], w=p.orientation[3]))
    return _serialize(T[POSE_STAMPED](header=_header(p.frame, p.stamp), pose=pose),
                      POSE_STAMPED)


def decode_odometry(payload: bytes | bytearray | memoryview, *,
                    max_bytes: int = 1 << 16) -> PoseFields:
    m = _deserialize(payload, ODOMETRY, max_bytes)
    pos, ori = _vec(m.pose.pose.position), _quat(m.pose.pose.orientation)
    _finite("the odometry pose", *pos, *ori)
    return PoseFields(str(m.header.frame_id), _stamp(m.header.stamp), pos, ori,
                      child=str(m.child_frame_id))


# -- tf2_msgs/msg/TFMessage ----------------------------------------------------------------
def decode_tf_message(payload: bytes | bytearray | memoryview, *,
                      max_bytes: int = 1 << 20) -> list[TransformFields]:
    return tf_fields(_deserialize(payload, TF_MESSAGE, max_bytes))


def tf_fields(m: Any) -> list[TransformFields]:
    """A rosbags TFMessage object -> its transforms (at most :data:`MAX_TRANSFORMS`)."""
    if len(m.transforms) > MAX_TRANSFORMS:
        raise Ros2DecodeError("too_large", f"{len(m.transforms)} transforms in one message "
                                           f"exceed {MAX_TRANSFORMS}")
    out = []
    for t in m.transforms:
        tr, rot = _vec(t.transform.translation), _quat(t.transform.rotation)
        _finite(f"the transform {t.header.frame_id} -> {t.child_frame_id}", *tr, *rot)
        out.append(TransformFields(str(t.header.frame_id), str(t.child_frame_id),
                                   _stamp(t.header.stamp), tr, rot))
    return out


def encode_tf_message(transforms: list[TransformFields]) -> bytes:
    T = typestore().types
    msgs = [T["geometry_msgs/msg/TransformStamped"](
        header=_header(t.parent, t.stamp), child_frame_id=t.child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t.translation[0], y=t.translation[1],
                                                       z=t.translation[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=t.rotation[0], y=t.rotation[1],
                                                       z=t.rotation[2], w=t.rotation[3])))
        for t in transforms]
    return _serialize(T[TF_MESSAGE](transforms=msgs), TF_MESSAGE)


# -- sensor_msgs/msg/LaserScan (bags) ------------------------------------------------------
def laser_scan_fields(m: Any) -> LaserScanFields:
    """A rosbags LaserScan object (from a bag reader) -> :class:`LaserScanFields`."""
    vals = (float(m.angle_min), float(m.angle_increment), float(m.range_min),
            float(m.range_max))
    _finite("the scan's angles or range limits", *vals)
    return LaserScanFields(str(m.header.frame_id), _stamp(m.header.stamp), *vals,
                           ranges=np.asarray(m.ranges, dtype=np.float32))


def decode_laser_scan(payload: bytes | bytearray | memoryview, *,
                      max_bytes: int = 1 << 22) -> LaserScanFields:
    return laser_scan_fields(_deserialize(payload, LASER_SCAN, max_bytes))


# -- nav_msgs/srv/GetMap -------------------------------------------------------------------
def decode_get_map_request(payload: bytes | bytearray | memoryview) -> None:
    """Check a GetMap request (it carries nothing): a CDR header, optionally the dummy byte."""
    raw = bytes(payload)
    if len(raw) == 4 and raw[:2] in (b"\x00\x01", b"\x00\x00"):
        return
    _deserialize(raw, GET_MAP_REQUEST, 64)


def encode_get_map_request() -> bytes:
    T = typestore().types
    return _serialize(T[GET_MAP_REQUEST](structure_needs_at_least_one_member=0),
                      GET_MAP_REQUEST)


def encode_get_map_response(g: OccupancyGridFields) -> bytes:
    T = typestore().types
    return _serialize(T[GET_MAP_RESPONSE](map=_grid_msg(g)), GET_MAP_RESPONSE)


def decode_get_map_response(payload: bytes | bytearray | memoryview, *,
                            max_bytes: int = DEFAULT_MAX_PAYLOAD,
                            max_cells: int = DEFAULT_MAX_CELLS) -> OccupancyGridFields:
    return grid_fields(_deserialize(payload, GET_MAP_RESPONSE, max_bytes).map, max_cells)
