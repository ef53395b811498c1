"""ROS 2 messages <-> this project's ISMs, grids and poses (pure, no zenoh).

Field mapping of an incoming ``nav_msgs/msg/OccupancyGrid`` (docs/ros2.md):
frame <- ``header.frame_id`` (a ROS 1 style leading ``/`` dropped); stamp <- ``header.stamp``;
resolution <- ``info.resolution``, a float32 on the wire, taken as the shortest decimal that
is the same float32 (0.0500000007 -> 0.05, so a grid at the map's resolution is not resampled);
origin <- ``info.origin`` (both conventions put it at the corner of cell (0, 0)) with the yaw of
its quaternion; a quaternion that tilts the grid by more than ``max_tilt`` radians is refused
(``non_planar``), one of (nearly) zero length too (``bad_quaternion``); cells <- ``data`` as
``occupancy_i8``; layer and robot <- the topic (:func:`.keys.topic_layer`).

The other way, a window of the map (probabilities or log-odds) becomes an OccupancyGrid with
0..100 and -1 where nothing is known (log-odds exactly 0).  Poses come from PoseStamped,
Odometry (``pose.pose``) or a chain of TF transforms (:class:`TfTree`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
import numpy.typing as npt

from sogm_service.adapters.ros2.cdr import OccupancyGridFields, PoseFields, Quat, TransformFields
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.wire.codec import DecodeError, validate
from sogm_service.wire.limits import MAX_ISM_CELLS
from sogm_service.wire.messages import IsmMessage

DEFAULT_MAX_TILT = 0.01
"""Largest tilt (rad, ~0.57 deg) of a grid's quaternion out of the plane that is still taken as
a rotation about z: a tilt of 0.01 shortens the projected cells by 5e-5."""

ValueKind = Literal["probability", "logodds", "fixed"]


def frame_id(frame: str) -> str:
    """A frame id without a ROS 1 style leading ``/``."""
    return frame.lstrip("/")


def float32_decimal(v: float) -> float:
    """The shortest decimal that is the same float32 (``0.0500000007`` -> ``0.05``)."""
    return float(str(np.float32(v)))


def quaternion_yaw(q: Quat, *, max_tilt: float | None = DEFAULT_MAX_TILT,
                   what: str = "quaternion") -> float:
    """Yaw (rad) of a quaternion ``(x, y, z, w)``.

    ``max_tilt`` set: refuse a rotation that is not about z (``non_planar``); ``None``: the yaw
    of the rotated x axis projected on the plane (robot poses on a slope).
    """
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n):
        raise Ros2DecodeError("non_finite", f"{what} {q} is not finite")
    if n < 1e-6:
        raise Ros2DecodeError("bad_quaternion", f"{what} {q} has (nearly) zero length")
    x, y, z, w = x / n, y / n, z / n, w / n
    if max_tilt is not None:
        cos_tilt = 1.0 - 2.0 * (x * x + y * y)  # z axis after the rotation, its z component
        tilt = math.acos(max(-1.0, min(1.0, cos_tilt)))
        if tilt > max_tilt:
            raise Ros2DecodeError("non_planar", f"{what} {q} tilts the plane by "
                                                f"{math.degrees(tilt):.2f} deg")
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quaternion(yaw: float) -> Quat:
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


# -- OccupancyGrid -> ISM ------------------------------------------------------------------
def grid_to_ism(g: OccupancyGridFields, *, layer: str | None = None, robot: str | None = None,
                max_tilt: float = DEFAULT_MAX_TILT,
                max_cells: int = MAX_ISM_CELLS) -> IsmMessage:
    """A decoded OccupancyGrid as the project's ISM (``occupancy_i8``), validated."""
    yaw = quaternion_yaw(g.orientation, max_tilt=max_tilt, what="info.origin.orientation")
    if not math.isfinite(g.resolution):
        raise Ros2DecodeError("non_finite", "info.resolution is not finite")
    if g.resolution <= 0:
        raise Ros2DecodeError("non_positive_resolution",
                              f"info.resolution must be > 0, got {g.resolution}")
    if g.width <= 0 or g.height <= 0:
        raise Ros2DecodeError("invalid_value", f"empty grid {g.width}x{g.height}")
    obj = {
        "layer": layer, "robot": robot, "frame": frame_id(g.frame), "stamp": float(g.stamp),
        "resolution": float32_decimal(g.resolution),
        "origin": {"x": float(g.position[0]), "y": float(g.position[1]), "yaw": float(yaw)},
        "width": int(g.width), "height": int(g.height), "encoding": "occupancy_i8",
        "data": np.ascontiguousarray(g.data, dtype=np.int8).tobytes(),
    }
    try:
        return validate(IsmMessage, obj, context={"max_cells": max_cells})
    except DecodeError as exc:
        raise Ros2DecodeError(exc.code, exc.message) from None


def ism_to_grid(msg: IsmMessage) -> OccupancyGridFields:
    """The other way (for tests and replays): an ``occupancy_i8`` ISM as an OccupancyGrid."""
    if msg.encoding != "occupancy_i8":
        raise ValueError(f"only occupancy_i8 ISMs map 1:1 to OccupancyGrid, not {msg.encoding}")
    return OccupancyGridFields(
        frame=msg.frame, stamp=msg.stamp, resolution=msg.resolution, width=msg.width,
        height=msg.height, position=(msg.origin.x, msg.origin.y, 0.0),
        orientation=yaw_quaternion(msg.origin.yaw), data=msg.array().copy())


# -- map window -> OccupancyGrid -----------------------------------------------------------
@lru_cache(maxsize=1)
def _fixed_occupancy_lut() -> npt.NDArray[np.int8]:
    l = np.arange(-logodds.MAX_STATE, logodds.MAX_STATE + 1, dtype=np.float64) / logodds.SCALE
    lut = np.rint(logodds.sigmoid(l) * 100.0).astype(np.int8)
    lut[logodds.MAX_STATE] = -1  # log-odds exactly 0: never observed
    lut.flags.writeable = False
    return lut


def occupancy_from_values(values: npt.ArrayLike, kind: ValueKind) -> npt.NDArray[np.int8]:
    """Probabilities, float log-odds (nats) or fixed log-odds -> 0..100, -1 unknown.

    Unknown is what the map never observed: log-odds exactly 0 (p exactly 0.5); NaN too.
    """
    a = np.asarray(values)
    if kind == "fixed":  # one lookup per cell (a 32001-entry table), 20x faster than sigmoid
        idx = np.clip(a, -logodds.MAX_STATE, logodds.MAX_STATE).astype(np.int32)
        idx += logodds.MAX_STATE
        return _fixed_occupancy_lut()[idx]
    if kind == "logodds":
        l = a.astype(np.float64)
        unknown = ~np.isfinite(l) | (l == 0)
        with np.errstate(invalid="ignore"):
            p = np.asarray(logodds.sigmoid(np.nan_to_num(l)), dtype=np.float64)
    elif kind == "probability":
        p = a.astype(np.float64)
        unknown = ~np.isfinite(p) | (p == 0.5)
    else:
        raise ValueError(f"unknown value kind {kind!r}")
    occ = np.rint(np.clip(np.nan_to_num(p, nan=0.5), 0.0, 1.0) * 100.0).astype(np.int8)
    occ[unknown] = -1
    return occ


def window_to_grid(values: npt.ArrayLike, geometry: GridGeometry, *,
                   kind: ValueKind = "logodds", frame: str = "map",
                   stamp: float = 0.0) -> OccupancyGridFields:
    """A ``(height, width)`` window of the map as an OccupancyGrid (origin: its cell (0, 0))."""
    occ = occupancy_from_values(values, kind)
    if occ.shape != geometry.shape:
        raise ValueError(f"values of shape {occ.shape}, geometry {geometry.shape}")
    o = geometry.origin
    return OccupancyGridFields(
        frame=frame, stamp=stamp, resolution=geometry.resolution, width=geometry.width,
        height=geometry.height, position=(o.x, o.y, 0.0), orientation=yaw_quaternion(o.yaw),
        data=occ)


def grid_geometry(g: OccupancyGridFields, max_tilt: float = DEFAULT_MAX_TILT) -> GridGeometry:
    yaw = quaternion_yaw(g.orientation, max_tilt=max_tilt)
    return GridGeometry(float32_decimal(g.resolution), g.width, g.height,
                        Pose2D(g.position[0], g.position[1], yaw))


# -- poses ---------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class RobotPose:
    robot: str
    x: float
    y: float
    yaw: float
    stamp: float


def pose_to_robot(p: PoseFields, robot: str, map_frame: str | None = "map") -> RobotPose:
    """A PoseStamped or Odometry pose of ``robot``; refused (``wrong_frame``) when its header
    frame is not ``map_frame`` (``None``: any frame is taken as the map's)."""
    if map_frame is not None and frame_id(p.frame) != frame_id(map_frame):
        raise Ros2DecodeError("wrong_frame", f"pose of {robot} in frame {p.frame!r}, not "
                                             f"{map_frame!r}")
    yaw = quaternion_yaw(p.orientation, max_tilt=None, what="pose orientation")
    return RobotPose(robot, p.position[0], p.position[1], yaw, p.stamp)


Matrix4 = npt.NDArray[np.float64]


def _matrix(translation: tuple[float, float, float], q: Quat) -> Matrix4:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 1e-6:
        raise Ros2DecodeError("bad_quaternion", f"transform rotation {q} has zero length")
    x, y, z, w = x / n, y / n, z / n, w / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = translation
    return m


@dataclass(frozen=True, slots=True)
class _Edge:
    parent: str
    matrix: Matrix4
    stamp: float
    static: bool


class TfTree:
    """The latest transform of every frame (no interpolation), and lookups along the tree.

    Each child frame has one parent (as in tf2); a newer transform of a child replaces the
    older one.  At most ``max_frames`` frames are kept: a transform that would add more is
    refused (``too_many_frames``) and the others of its message still apply.
    """

    def __init__(self, map_frame: str = "map", robot_frame: str = "{robot}/base_link",
                 max_frames: int = 1024) -> None:
        self.map_frame = frame_id(map_frame)
        self.robot_frame = frame_id(robot_frame)
        pattern = re.escape(self.robot_frame).replace(re.escape("{robot}"), "([^/]+)")
        self._robot_re = re.compile(f"^{pattern}$")
        self.max_frames = max_frames
        self._edges: dict[str, _Edge] = {}

    def __len__(self) -> int:
        return len(self._edges)

    def robot_of(self, frame: str) -> str | None:
        m = self._robot_re.match(frame_id(frame))
        return m[1] if m and m.groups() else None

    def set(self, transforms: Iterable[TransformFields], static: bool = False) -> set[str]:
        """Store transforms; returns the child frames that changed."""
        changed: set[str] = set()
        refused = 0
        for t in transforms:
            child, parent = frame_id(t.child), frame_id(t.parent)
            if not child or not parent or child == parent:
                continue
            if child not in self._edges and len(self._edges) >= self.max_frames:
                refused += 1
                continue
            self._edges[child] = _Edge(parent, _matrix(t.translation, t.rotation), t.stamp,
                                       static)
            changed.add(child)
        if refused:
            raise Ros2DecodeError("too_many_frames", f"{refused} transforms refused: the tree "
                                                     f"holds its limit of {self.max_frames}")
        return changed

    def _to_root(self, frame: str) -> tuple[list[str], Matrix4, float]:
        """Chain of frames from ``frame`` to its root, the root->frame transform, newest
        dynamic stamp."""
        chain = [frame]
        m = np.eye(4)
        stamp = -math.inf
        static_stamp = -math.inf
        f = frame
        while f in self._edges:
            e = self._edges[f]
            m = e.matrix @ m
            if e.static:
                static_stamp = max(static_stamp, e.stamp)
            else:
                stamp = max(stamp, e.stamp)
            f = e.parent
            if f in chain or len(chain) > self.max_frames:
                raise Ros2DecodeError("invalid_value", f"the transform tree has a loop at {f!r}")
            chain.append(f)
        return chain, m, stamp if stamp > -math.inf else max(static_stamp, 0.0)

    def lookup(self, target: str, source: str) -> tuple[Matrix4, float] | None:
        """Transform of ``source`` in ``target`` (4x4) and its stamp, None if not connected."""
        target, source = frame_id(target), frame_id(source)
        src_chain, src_m, src_t = self._to_root(source)
        tgt_chain, tgt_m, tgt_t = self._to_root(target)
        if src_chain[-1] != tgt_chain[-1]:
            return None
        return np.asarray(np.linalg.solve(tgt_m, src_m), dtype=np.float64), max(src_t, tgt_t)

    def lookup_planar(self, target: str, source: str) -> tuple[Pose2D, float] | None:
        found = self.lookup(target, source)
        if found is None:
            return None
        m, stamp = found
        return Pose2D(float(m[0, 3]), float(m[1, 3]), math.atan2(m[1, 0], m[0, 0])), stamp

    def robot_frames(self) -> dict[str, str]:
        """robot name -> its frame, for every known frame that matches the robot pattern."""
        out: dict[str, str] = {}
        for f in self._edges:
            robot = self.robot_of(f)
            if robot is not None:
                out[robot] = f
        return out

    def update(self, transforms: Iterable[TransformFields],
               static: bool = False) -> list[RobotPose]:
        """Store transforms and return the map pose of each robot whose chain changed."""
        changed = self.set(transforms, static)
        poses = []
        for robot, frame in sorted(self.robot_frames().items()):
            chain, _, _ = self._to_root(frame)
            if not changed.intersection(chain):
                continue
            found = self.lookup_planar(self.map_frame, frame)
            if found is not None:
                pose, stamp = found
                poses.append(RobotPose(robot, pose.x, pose.y, pose.yaw, stamp))
        return poses
