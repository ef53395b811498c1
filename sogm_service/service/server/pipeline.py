"""The ingestion pipeline: one ISM from its Zenoh payload to the tiles, each step once.

Architecture, section 3 (docs/architecture.md#3-the-two-data-paths), in this order and nowhere else:

1. **decode and validate** the payload (:mod:`sogm_service.wire.codec`, the pydantic model);
2. **prepare**: the layer name (the ``layer`` field or the key's remainder), the frame check,
   fixed log-odds increments (a 256-entry lookup table for 8-bit encodings) and the geometry;
3. **bound checks** from the header alone
   (:class:`~sogm_service.service.server.admission.Admission`:
   world extent, tiles touched, names, layers, robots, memory without a store);
4. **align**: scan matching per the source's policy
   (:class:`~sogm_service.service.server.matcher.Matcher`)
5. **fuse**: Eq. 1 into every tile the ISM overlaps
   (:meth:`~sogm_service.core.map.tiles.TiledMap.fuse`)
6. **tile bookkeeping**: the fleet tracker follows the ISM's robot, the memory budget is kept.

Each refusal is a :class:`~sogm_service.wire.errors.SogmError` whose ``code`` is counted and
logged once (:class:`~sogm_service.service.server.stats.Rejections`); the map is unchanged by it.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.core.resample import Interp
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.acks import IsmOutcomes
from sogm_service.service.server.admission import Admission
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.fleet import FleetTracker
from sogm_service.service.server.fusers import FuseJob, FuseWorkers, ism_digest
from sogm_service.service.server.matcher import Matcher
from sogm_service.service.server.stats import Rejections, Stats
from sogm_service.wire import codec
from sogm_service.wire.errors import IsmRejectedError, SogmError
from sogm_service.wire.keys import key_remainder, robot_of_ism_key
from sogm_service.wire.limits import LAYER_NAME_PATTERN
from sogm_service.wire.messages import IsmHeader, IsmMessage

log = logging.getLogger(__name__)

_LAYER_NAME = re.compile(LAYER_NAME_PATTERN)
NAMES_KEPT = 4096
"""ISM keys whose robot and layer name the pipeline remembers (a fleet has a few per robot)."""


@dataclass(frozen=True, slots=True)
class IsmItem:
    """A received ISM as the Zenoh callback queues it: which source, which key, the bytes.

    An adapter (ROS 2) that decoded its own format queues the message instead (``msg``), with
    the layer and robot its topic names."""

    source: int
    key: str
    payload: bytes = b""
    msg: IsmMessage | None = None
    layer: str = ""
    robot: str | None = None
    ism_id: str | None = None  # asks for an acknowledgement (service/server/acks.py)


@dataclass(frozen=True, slots=True)
class PreparedIsm:
    """An ISM ready to fuse: its message, layer, increments and where they lie."""

    msg: IsmMessage
    key: str
    source: int
    layer: str
    increments: npt.NDArray[np.int16]
    geometry: GridGeometry


def layer_name(msg: IsmHeader, key: str, key_expr: str) -> str:
    """The ISM's layer: its ``layer`` field, else the key's remainder after the literal prefix."""
    name = msg.layer or key_remainder(key, key_expr)
    if not _LAYER_NAME.match(name):
        raise IsmRejectedError("bad_layer", f"layer name {name!r} is empty, too long or has "
                                            "characters outside [A-Za-z0-9_-./]", "layer")
    return name


def check_robot(named: str | None, by_key: str) -> None:
    """A message may name only the robot of its key: access control grants keys per robot
    (``ism/<robot>/**``, ``pose/<robot>``), so the name in a payload is trusted no further."""
    if named is not None and named != by_key:
        raise IsmRejectedError("robot_mismatch", f"the message names robot {named[:64]!r} on "
                                                 f"a key of robot {by_key[:64]!r}", "robot")


def ism_geometry(msg: IsmHeader) -> GridGeometry:
    return GridGeometry(msg.resolution, msg.width, msg.height,
                        Pose2D(msg.origin.x, msg.origin.y, msg.origin.yaw))


def check_frame(msg: IsmHeader, frame: str) -> None:
    if msg.frame != frame:
        raise IsmRejectedError("wrong_frame",
                               f"ISM frame {msg.frame!r} is not the map frame {frame!r}", "frame")


def increments(msg: IsmMessage, frame: str, eps0: float) -> npt.NDArray[np.int16]:
    """The ISM's fixed log-odds increments, once its frame is checked against the map's."""
    check_frame(msg, frame)
    return logodds.increments(msg.array(), msg.encoding, eps0)


def fuse_ism(tiled: TiledMap, msg: IsmMessage, layer: str,
             interp: Interp = "biodds") -> list[TileIndex]:
    """Eq. 1 for one ISM as it claims to be placed, in one process (tests, benchmarks): steps
    2 and 5 of the pipeline, without matching and bookkeeping."""
    inc = increments(msg, tiled.frame, tiled.eps0)
    return tiled.fuse(layer, inc, ism_geometry(msg), interp, msg.stamp)


class IngestPipeline:
    """Runs the steps of the module docstring for one queued ISM at a time; the fuse itself
    goes to the :class:`~sogm_service.service.server.fusers.FuseWorkers` (several threads over
    disjoint tiles), and the bookkeeping runs when the last of them is done."""

    def __init__(self, config: ServiceConfig, tiled: TiledMap, stats: Stats,
                 matcher: Matcher, fleet: FleetTracker, tiles: Checkpointer,
                 fusers: FuseWorkers) -> None:
        self.config = config
        self.tiled = tiled
        self.stats = stats
        self.matcher = matcher
        self.fleet = fleet
        self.tiles = tiles
        self.fusers = fusers
        self.rejections = Rejections(stats, config.limits.log_text_chars)
        self.admission = Admission(config, stats)
        self.admission.store_backlog = tiles.writer_full
        # What became of each ISM, for its publisher (service/server/acks.py); set by the server.
        self.outcomes: IsmOutcomes | None = None
        # A cluster member: whether it owns none of the tiles of a footprint's box (then the
        # ISM is another member's to fuse: no increments, no fuse).  Set by the server.
        self.owns_none: Callable[[tuple[int, int, int, int]], bool] | None = None
        self._names: dict[tuple[int, str, str | None], tuple[str, str]] = {}

    def handle(self, item: IsmItem) -> None:
        """Decode, validate, prepare, check and align one ISM, then hand it to the fuse
        workers; a refusal at any step is counted with its reason and changes nothing."""
        started = time.perf_counter()
        try:
            msg = self.decode(item) if self.owns_none is None else self._decode_owned(item)
            if msg is None:
                return  # another member's to fuse: its header is checked and followed
            ism = self.prepare(item, msg)
            reserved = self.admission.check_ism(msg, ism.layer, msg.robot, self.tiled,
                                                self.fleet)
            self._submit(item, ism, started, reserved)
        except SogmError as exc:
            self.rejections.reject(exc.code, f"{item.key}: {exc}")
            self.report(item, exc.code, str(exc))
        except Exception as exc:  # never let one ISM kill the worker
            log.exception("internal error on ISM from %s", item.key[:200])
            self.rejections.reject("internal_error", f"{item.key}: {type(exc).__name__}: {exc}")
            self.report(item, "internal_error", f"{type(exc).__name__}: {exc}")

    def _submit(self, item: IsmItem, ism: PreparedIsm, started: float, reserved: int) -> None:
        """Align and hand to the fuse workers; the reservation goes with the job (released
        when it is fused) or is released here when that fails."""
        try:
            ism = self.align(ism)
            self.tiled.layer_id(ism.layer, create=True)  # layers in arrival order, any K
            self.fusers.submit(FuseJob(
                ism.layer, ism.increments, ism.geometry, self.config.ism[ism.source].interp,
                ism.msg.stamp, done=partial(self._fused, ism, started, item=item,
                                            reserved=reserved),
                **self.identity(item, ism.msg)))
        except BaseException:
            self.admission.release(reserved)
            raise

    def _decode_owned(self, item: IsmItem) -> IsmMessage | None:
        """A cluster member checks a zstd ISM's frame from its header and decompresses it only
        when it owns one of the ISM's tiles: the decompression and the cells' value checks
        are the owners' work (raw cells are checked whole by every member).  None when the
        ISM is another member's."""
        if item.msg is not None:
            return None if self._elsewhere(item, item.msg) else item.msg
        fields = codec.unpack(item.payload)
        context = {"max_cells": self.config.limits.max_ism_cells}
        sent = codec.validate(IsmMessage, fields, {**context, "framing_only": True})
        if self._elsewhere(item, sent):
            return None
        return sent if sent.compression is None else codec.validate(IsmMessage, fields, context)

    def _elsewhere(self, item: IsmItem, msg: IsmHeader) -> bool:
        """A cluster member that owns none of the ISM's tiles only checks its header and
        follows its robot: the increments and the fuse are other members' work."""
        assert self.owns_none is not None
        if not self.owns_none(self.admission.footprint(msg).tiles):
            return False
        # The owners' header checks, so that every member refuses alike (the map-state ones,
        # layer count and memory, are the owners').
        layer = self.identify(item, msg)
        self.admission.check_names(layer, msg.robot)
        self.admission.check_stamp(msg.stamp, layer, self.tiled.now())
        check_frame(msg, self.tiled.frame)
        if msg.robot:
            self.fleet.check_robot(msg.robot)
        x, y = ism_geometry(msg).centre()
        self.fleet.ism_centre(msg.robot, x, y, msg.stamp)
        self.tiled.advance_clock(msg.stamp)  # decaying layers read alike on every member
        self.stats.count("cluster_isms_elsewhere")
        self.stats.fused()  # handled: fused by the members that own its tiles
        self.report(item, None, "fused")
        return True

    def decode(self, item: IsmItem) -> IsmMessage:
        if item.msg is not None:  # decoded and validated by its adapter
            return item.msg
        return codec.decode(IsmMessage, item.payload,
                            context={"max_cells": self.config.limits.max_ism_cells})

    def identify(self, item: IsmItem, msg: IsmHeader) -> str:
        """The ISM's layer, once its robot is checked against its key's."""
        source = self.config.ism[item.source]
        if item.msg is not None:  # decoded by its adapter
            check_robot(msg.robot, item.robot or msg.robot or "")
            return layer_name(msg.model_copy(update={"layer": item.layer or msg.layer}),
                              item.key, source.key_expr)
        named = (item.source, item.key, msg.layer)
        known = self._names.get(named)
        if known is None:  # each key's robot and layer once: every member sees every ISM
            known = (robot_of_ism_key(item.key, source.key_expr),
                     layer_name(msg, item.key, source.key_expr))
            if len(self._names) >= NAMES_KEPT:
                self._names.clear()  # keys are the publishers' to choose: kept bounded
            self._names[named] = known
        check_robot(msg.robot, known[0])
        return known[1]

    def prepare(self, item: IsmItem, msg: IsmMessage) -> PreparedIsm:
        layer = self.identify(item, msg)
        inc = increments(msg, self.tiled.frame, self.config.map.eps0)
        return PreparedIsm(msg, item.key, item.source, layer, inc, ism_geometry(msg))

    def align(self, ism: PreparedIsm) -> PreparedIsm:
        """Scan matching per the source's policy: the ISM where it is to be fused.  Matching
        reads the map, so it waits until the ISMs before this one are fused."""
        if not self.matcher.enabled(ism.source):
            return ism
        self.fusers.drain()
        inc, geometry = self.matcher.place(self.tiled, ism.msg, ism.key, ism.layer, ism.source,
                                           ism.increments, ism.geometry)
        return replace(ism, increments=inc, geometry=geometry)

    def _fused(self, ism: PreparedIsm, started: float, touched: list[TileIndex],
               error: BaseException | None, item: IsmItem | None = None,
               reserved: int = 0) -> None:
        """The last fuse worker is done with ``ism``: count it and do the bookkeeping."""
        self.admission.release(reserved)  # its tiles are resident now (or it failed)
        if error is not None:
            log.error("internal error fusing the ISM from %s: %r", ism.key, error)
            self.rejections.reject("internal_error",
                                   f"{ism.key}: {type(error).__name__}: {error}")
            self.report(item, "internal_error", f"{type(error).__name__}: {error}")
            return
        try:
            self.bookkeeping(ism, touched)
        except Exception as exc:
            log.exception("internal error after fusing the ISM from %s", ism.key)
            self.rejections.reject("internal_error", f"{ism.key}: {type(exc).__name__}: {exc}")
            self.report(item, "internal_error", f"{type(exc).__name__}: {exc}")
            return
        self.stats.fused()
        self.report(item, None, "fused")
        self.stats.latency("fuse", time.perf_counter() - started)

    def bookkeeping(self, ism: PreparedIsm, touched: list[TileIndex]) -> None:
        x, y = ism.geometry.centre()
        self.fleet.ism_centre(ism.msg.robot, x, y, ism.msg.stamp)
        if touched:
            self.tiles.enforce_budget()

    def identity(self, item: IsmItem, msg: IsmMessage) -> dict[str, Any]:
        """A cluster member's fuse job carries the ISM's key and a digest of it (the cluster's
        handover replays journaled ISMs by it); nothing otherwise."""
        if not self.config.cluster.enabled:
            return {}
        payload = item.payload or bytes(msg.data) + repr(msg.stamp).encode()
        return {"key": item.key, "digest": ism_digest(payload)}

    def report(self, item: IsmItem | None, code: str | None, message: str) -> None:
        """Tell the ISM's publisher: fused (``code`` None) or rejected (service/server/acks.py)."""
        if self.outcomes is not None and item is not None:
            self.outcomes.outcome(item.key, item.source, item.ism_id, code, message)
