"""Reading ROS bags (ROS 1 ``.bag``, ROS 2 sqlite3 and mcap) with rosbags' ``AnyReader``.

What a bag gives the map server:

* ``sensor_msgs/msg/LaserScan`` -> :class:`~sogm_service.adapters.carmen.LaserScan` (the same
  type the CARMEN reader yields, so :func:`~sogm_service.adapters.carmen.scan_ism` and the
  replay path apply unchanged), placed by the latest ``/tf`` and ``/tf_static`` transforms
  from the map frame to the scan's ``header.frame_id`` at the time the scan is read (no
  interpolation; a bag's transforms come at tens of Hz).  Scans whose frame is not yet
  connected to the map frame are skipped and counted (``unlocalized``).
* ``nav_msgs/msg/OccupancyGrid`` -> :class:`~sogm_service.wire.messages.IsmMessage`, exactly
  as from rmw_zenoh (:func:`~sogm_service.adapters.ros2.convert.grid_to_ism`); the layer and
  robot come from the topic under ``ism_prefix`` (``/ism/robot1/obstacle`` -> layer
  ``robot1/obstacle``), or the topic itself without its outer ``/`` when it is elsewhere.

:class:`BagReader` knows the total number of messages it reads before it starts
(:attr:`BagReader.total`, from the bag's index), and each yielded item carries how many
messages were consumed so far (:attr:`BagScan.position`), which is what a progress bar needs.
Bad messages are skipped and counted per code, never raised.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.adapters.carmen import LaserScan
from sogm_service.adapters.ros2.cdr import (
    OccupancyGridFields,
    grid_fields,
    laser_scan_fields,
    tf_fields,
    typestore,
)
from sogm_service.adapters.ros2.convert import DEFAULT_MAX_TILT, TfTree, frame_id, grid_to_ism
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import LASER_SCAN, OCCUPANCY_GRID, TF_MESSAGE, topic_layer
from sogm_service.core.geometry import Pose2D
from sogm_service.wire.limits import MAX_ISM_CELLS
from sogm_service.wire.messages import IsmMessage

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BagScan:
    topic: str
    scan: LaserScan
    position: int  # messages consumed so far, this one included


@dataclass(frozen=True)
class BagGrid:
    topic: str
    layer: str
    ism: IsmMessage
    position: int


BagItem = BagScan | BagGrid


@dataclass
class BagStats:
    messages: int = 0
    scans: int = 0
    grids: int = 0
    transforms: int = 0
    unlocalized: int = 0
    rejected: Counter[str] = field(default_factory=Counter)

    def summary(self) -> str:
        """One line: what was read and what was passed over, by reason."""
        refused = ", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "none"
        return (f"messages: {self.messages}; scans {self.scans}, grids {self.grids}, "
                f"transforms {self.transforms}; unlocalized scans {self.unlocalized}; "
                f"refused: {refused}")


class BagReader:
    """Iterate a bag's scans (with TF poses) and grids; ``len()`` is the messages it reads.

    ``scan_topics`` / ``grid_topics``: ``None`` takes every topic of the type.
    """

    def __init__(self, paths: str | Path | Sequence[str | Path], *, map_frame: str = "map",
                 scan_topics: Sequence[str] | None = None,
                 grid_topics: Sequence[str] | None = None,
                 tf_topics: Sequence[str] = ("/tf", "/tf_static"),
                 ism_prefix: str = "/ism", max_tilt: float = DEFAULT_MAX_TILT,
                 max_cells: int = MAX_ISM_CELLS) -> None:
        from rosbags.highlevel import AnyReader  # the import costs ~0.1 s; only when used

        ps = [paths] if isinstance(paths, (str, Path)) else list(paths)
        self._reader = AnyReader([Path(p) for p in ps], default_typestore=typestore())
        self.map_frame = frame_id(map_frame)
        self.ism_prefix = ism_prefix
        self.max_tilt = max_tilt
        self.max_cells = max_cells
        self.stats = BagStats()
        self._reader.open()
        try:
            conns = self._reader.connections
            self._scans = [c for c in conns if c.msgtype == LASER_SCAN
                           and (scan_topics is None or c.topic in scan_topics)]
            self._grids = [c for c in conns if c.msgtype == OCCUPANCY_GRID
                           and (grid_topics is None or c.topic in grid_topics)]
            self._tf = [c for c in conns if c.msgtype == TF_MESSAGE and c.topic in tf_topics]
        except BaseException:
            self._reader.close()
            raise
        self.total = sum(c.msgcount for c in (*self._scans, *self._grids, *self._tf))

    def __len__(self) -> int:
        return self.total

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def topics(self) -> dict[str, list[str]]:
        """The topics read, by role."""
        return {"scans": sorted({c.topic for c in self._scans}),
                "grids": sorted({c.topic for c in self._grids}),
                "tf": sorted({c.topic for c in self._tf})}

    def __iter__(self) -> Iterator[BagItem]:
        tree = TfTree(self.map_frame, "{robot}")
        conns = [*self._scans, *self._grids, *self._tf]
        if not conns:
            return
        st = self.stats
        for conn, _t, raw in self._reader.messages(connections=conns):
            st.messages += 1
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # a corrupt record: skip it, never stop the replay
                st.rejected["bad_cdr"] += 1
                log.debug("%s: undecodable %s: %s", conn.topic, conn.msgtype, exc)
                continue
            try:
                item = self._handle(tree, conn.topic, conn.msgtype, msg)
            except Ros2DecodeError as exc:
                st.rejected[exc.code] += 1
                log.debug("%s: %s", conn.topic, exc)
                continue
            if item is not None:
                yield item

    def _handle(self, tree: TfTree, topic: str, msgtype: str, msg: Any) -> BagItem | None:
        st = self.stats
        pos = st.messages
        if msgtype == TF_MESSAGE:
            transforms = tf_fields(msg)
            st.transforms += len(transforms)
            tree.set(transforms, static=topic.endswith("_static"))
            return None
        if msgtype == LASER_SCAN:
            f = laser_scan_fields(msg)
            found = tree.lookup_planar(self.map_frame, f.frame)
            if found is None:
                st.unlocalized += 1
                return None
            pose: Pose2D = found[0]
            n = f.ranges.size
            angles = (f.angle_min + f.angle_increment * np.arange(n)).astype(np.float32)
            ranges = f.ranges.astype(np.float32)
            if f.range_min > 0:
                ranges = np.where(ranges < f.range_min, np.float32(np.nan), ranges)
            max_range = f.range_max if f.range_max > 0 and math.isfinite(f.range_max) else 1e3
            st.scans += 1
            return BagScan(topic, LaserScan(f.stamp, pose, ranges, angles, float(max_range)),
                           pos)
        g: OccupancyGridFields = grid_fields(msg, self.max_cells)
        try:
            layer, robot = topic_layer(topic, self.ism_prefix)
        except Ros2DecodeError:
            layer, robot = topic_layer(topic, "")
        ism = grid_to_ism(g, layer=layer, robot=robot, max_tilt=self.max_tilt,
                          max_cells=self.max_cells)
        st.grids += 1
        return BagGrid(topic, layer, ism, pos)
