"""Python client of a sogm-service map server.

>>> from sogm_service.client import MapClient
>>> with MapClient.connect("tcp/127.0.0.1:7447", map_name="default") as client:
...     sub = client.submap(x=0, y=0, width=10, height=10, resolution=0.1)
...     sub.probabilities().shape            # (layers, rows, cols)

Results carry their geometry so they can be placed without guessing; error replies raise
:class:`ServiceError` (with the server's ``code`` and the ``parameter`` at fault) and silence
raises :class:`QueryTimeoutError`.
"""

from __future__ import annotations

import itertools
import math
import secrets
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import numpy.typing as npt
import zenoh
from pydantic import BaseModel

from sogm_service.client.isms import IsmFootprint, build_ism, ism_footprint
from sogm_service.client.mirror import TileMirror
from sogm_service.client.offline import HeldIsm, OfflinePolicy, OfflineStats
from sogm_service.client.results import GridResult, grid_result, service_error
from sogm_service.client.session import (
    DEFAULT_ENDPOINT,
    ZenohSettings,
    check_endpoint,
    loopback_settings,
    open_session,
)
from sogm_service.core.geometry import Pose2D
from sogm_service.wire import codec, encodings
from sogm_service.wire import compression as zstd
from sogm_service.wire.compression import Compression
from sogm_service.wire.errors import (
    ConnectError,
    IsmNotFusedError,
    QueryTimeoutError,
    ServiceError,
    SessionOpenError,
)
from sogm_service.wire.keys import MapKeys, drop_chunks, last_chunk, pose_key, tile_of_key
from sogm_service.wire.limits import MAX_REPLY_BYTES, SUPERCELLS_TIMEOUT_S
from sogm_service.wire.messages import (
    DropLayersReply,
    GeodeticFix,
    IsmAck,
    IsmMessage,
    PoseMessage,
    RejectionReport,
    RobotTilesReply,
    TileEvent,
)
from sogm_service.wire.queries import FusedReply, GridReply, InfoReply, StatsReply, SupercellReply

M = TypeVar("M", bound=BaseModel)

DEFAULT_TIMEOUT_S = 5.0
"""Default budget of a query (supercells: :data:`SUPERCELLS_TIMEOUT_S`)."""

WAIT_FUSED_TIMEOUT_S = 15.0
"""Default budget of :meth:`MapClient.wait_fused` (a busy server's queue drains first)."""

RETRY_PAUSE_S = (0.05, 0.5)
"""A query without any reply (no route yet: a drop-out) is asked again after 50 ms, doubling
to 500 ms, until its budget is spent."""


class MapClient:
    """Queries and publishes against one map (``<prefix>/<map>/...``) over a Zenoh session."""

    def __init__(self, session: zenoh.Session, map_name: str = "default", prefix: str = "sogm",
                 timeout: float = DEFAULT_TIMEOUT_S, owns_session: bool = False) -> None:
        self.session = session
        self.map_name = map_name
        self.prefix = prefix.strip("/")
        self.timeout = timeout
        self._owns_session = owns_session
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.supercells_timeout = max(timeout, SUPERCELLS_TIMEOUT_S)
        self._id_prefix = secrets.token_hex(6)  # ISM ids: <prefix>-<n>, unique per client
        self._ids = itertools.count(1)
        self._pending: dict[str, str] = {}  # ISM id -> key, until wait_fused hears back
        # zstd for ISMs sent and window replies asked (grids compress 10-70x on thin links);
        # None: raw, for servers older than schema version 3.
        self.compression: Compression | None = zstd.ZSTD
        self.max_reply_bytes = MAX_REPLY_BYTES  # a compressed reply may expand to this much
        self.offline = OfflinePolicy(self._publisher, self._forget)  # keys without a route
        self._dropped: dict[str, str] = {}  # ISM id -> key, dropped by the offline policy

    @classmethod
    def connect(cls, endpoint: str | None = None, map_name: str = "default",
                prefix: str = "sogm", timeout: float = DEFAULT_TIMEOUT_S,
                zenoh_settings: ZenohSettings | None = None,
                zenoh_config: str | Path | zenoh.Config | None = None) -> MapClient:
        """Open an own session (closed by :meth:`close`): to ``endpoint`` as a client, with the
        given settings, or from a Zenoh config (a JSON5 file or a ``zenoh.Config``, honoured as
        it is: mode, TLS, endpoints; e.g. one written by ``sogm-service certs``)."""
        if zenoh_config is not None:
            try:
                config = zenoh_config if isinstance(zenoh_config, zenoh.Config) \
                    else zenoh.Config.from_file(str(zenoh_config))
                return cls(zenoh.open(config), map_name, prefix, timeout, owns_session=True)
            except zenoh.ZError as exc:
                first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                raise ConnectError(f"cannot open a Zenoh session with {zenoh_config}: "
                                   f"{first[:200]}", "zenoh_config") from None
        if zenoh_settings is None:
            where = endpoint or DEFAULT_ENDPOINT
            why = check_endpoint(where)
            if why is not None:
                raise ConnectError(why, "endpoint")
            settings = loopback_settings(connect=where, mode="client")
        else:
            settings = zenoh_settings
        try:
            return cls(open_session(settings), map_name, prefix, timeout, owns_session=True)
        except SessionOpenError as exc:
            if zenoh_settings is None:
                raise ConnectError(f"no sogm-service reachable at {where}: is 'sogm-service "
                                   "serve' running?", "endpoint") from None
            raise ConnectError(exc.message, exc.parameter) from None

    def close(self) -> None:
        self._forget(self.offline.buffer.discard())  # held ISMs whose route never returned
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        if self._owns_session:
            self.session.close()

    def __enter__(self) -> MapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- queries --------------------------------------------------------------------------
    def key(self, *parts: str) -> str:
        return MapKeys(self.prefix, self.map_name).key(*parts)

    def get_raw(self, key: str, params: dict[str, Any] | None = None,
                timeout: float | None = None) -> bytes:
        """One reply's payload from ``key`` (error replies raise :class:`ServiceError`)."""
        selector = key
        if params:
            selector += "?" + ";".join(f"{k}={_param(v)}" for k, v in params.items()
                                      if v is not None)
        budget = timeout or self.timeout
        deadline, pause = time.monotonic() + budget, RETRY_PAUSE_S[0]
        while True:
            left = max(deadline - time.monotonic(), 0.05)
            for reply in self.session.get(selector, timeout=left):
                if reply.ok is not None:
                    payload = reply.ok.payload.to_bytes()
                    if str(reply.ok.encoding).endswith(";" + encodings.ZSTD_SCHEMA):
                        return zstd.decompress_at_most(payload, self.max_reply_bytes)
                    return payload
                if reply.err is not None:
                    payload = reply.err.payload.to_bytes()
                    if payload == b"Timeout":  # Zenoh's: the queryable did not answer in time
                        raise QueryTimeoutError(f"{key}: no answer within {budget:g} s")
                    raise service_error(payload)
            # No reply at all: no route to a server (yet); a link coming back within the
            # budget answers the next try.  Service errors above are never asked again.
            if time.monotonic() + pause >= deadline:
                break
            time.sleep(pause)
            pause = min(pause * 2, RETRY_PAUSE_S[1])
        raise QueryTimeoutError(f"no reply from {key} within {budget:g} s: is a server of map "
                                f"{self.map_name!r} running and reachable?")

    def _get(self, cls: type[M], name: str, params: dict[str, Any] | None = None) -> M:
        return codec.decode(cls, self.get_raw(self.key(name), params))

    def submap(self, *, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, width: float = 10.0,
               height: float = 10.0, resolution: float | None = None,
               layers: list[str] | None = None, interp: str = "biodds",
               encoding: str = "prob_f32") -> GridResult:
        """The chosen layers (default all) resampled into a window centred on ``(x, y)``.

        Each entry of ``layers`` is a layer's name or a glob pattern naming a class
        (``"*/laser/obstacle"``: every robot's laser obstacles), whose matching layers come
        back fused by the Bayesian rule as one plane named by the pattern; the result's
        ``classes`` lists each pattern's members.  A name or pattern matching no layer is
        refused (``unknown_layer``)."""
        params = dict(x=x, y=y, yaw=yaw, width=width, height=height, resolution=resolution,
                      layers=layers, interp=interp, encoding=encoding,
                      compression=self.compression)
        return grid_result(self._get(GridReply, "submap", params))

    def fused(self, *, method: str = "bayes", x: float = 0.0, y: float = 0.0, yaw: float = 0.0,
              width: float = 10.0, height: float = 10.0, resolution: float | None = None,
              layers: list[str] | None = None, interp: str = "biodds",
              encoding: str = "prob_f32") -> GridResult:
        """Eq. 6 over the chosen layers: ``bayes`` (P_B) or ``max`` (P_M).  A glob pattern
        in ``layers`` pools its class (its layers' Bayesian fusion) as one layer: ``method``
        then pools the classes, e.g. ``layers=["*/laser/obstacle", "*/camera/person"]``."""
        params = dict(method=method, x=x, y=y, yaw=yaw, width=width, height=height,
                      resolution=resolution, layers=layers, interp=interp, encoding=encoding,
                      compression=self.compression)
        return grid_result(self._get(FusedReply, "fused", params))

    def supercells(self, timeout: float | None = None, **params: Any) -> SupercellReply:
        """The SEVDS topometric graph of a window (same window parameters + SEVDS's; a glob
        pattern in ``layers`` is one class, one entry of each node's feature vector).

        Waits up to ``timeout`` (default :attr:`supercells_timeout`, 90 s) in all: a server
        that is still compiling its kernels (the first start after an install) answers
        ``warming_up`` and is asked again."""
        deadline = time.monotonic() + (timeout or self.supercells_timeout)
        params.setdefault("compression", self.compression)
        while True:
            remaining = deadline - time.monotonic()
            try:
                payload = self.get_raw(self.key("supercells"), params,
                                       timeout=max(remaining, 0.5))
                return codec.decode(SupercellReply, payload)
            except ServiceError as exc:
                if exc.code != "warming_up":
                    raise
                if time.monotonic() + 0.2 >= deadline:
                    raise QueryTimeoutError(
                        f"supercells: the server was still compiling its kernels after "
                        f"{timeout or self.supercells_timeout:g} s") from None
                time.sleep(0.2)

    def drop_layers(self, pattern: str) -> DropLayersReply:
        """Remove the layers matching glob ``pattern`` (``robot3/*``) from the map and store:
        what went.  Denied by access control: no reply, a timeout (docs/using.md)."""
        return self._get(DropLayersReply, "drop/" + drop_chunks(pattern))

    def info(self) -> InfoReply:
        return self._get(InfoReply, "info")

    def stats(self) -> StatsReply:
        return self._get(StatsReply, "stats")

    def robots(self) -> RobotTilesReply:
        """Each robot's current tile (its last tile-switch event)."""
        return self._get(RobotTilesReply, "robots")

    def mirror(self, x: float, y: float, width: float, height: float,
               timeout: float | None = None) -> TileMirror:
        """A local copy of the tiles a box of the map frame (centre ``x``, ``y``; m) overlaps;
        its :meth:`~TileMirror.refresh` pulls only the tiles that changed
        (:mod:`sogm_service.client.mirror`).  Asks ``info`` once for the lattice."""
        return TileMirror(self.session, MapKeys(self.prefix, self.map_name), self.info(), x, y,
                          width, height, timeout or self.timeout)

    def tiles(self, i: int | None = None, j: int | None = None,
              timeout: float | None = None) -> dict[tuple[int, int], bytes]:
        """Whole tiles in the store's file format (:mod:`sogm_service.store.format`): one
        tile, or
        every tile of the map when ``i``/``j`` are omitted."""
        key = self.key("tiles", "**") if i is None or j is None else \
            self.key("tiles", str(i), str(j))
        out: dict[tuple[int, int], bytes] = {}
        for reply in self.session.get(key, timeout=timeout or self.timeout):
            if reply.ok is None:
                continue
            out[tile_of_key(str(reply.ok.key_expr))] = reply.ok.payload.to_bytes()
        return out

    def subscribe_tile_events(self, callback: Callable[[TileEvent], None]) -> zenoh.Subscriber:
        """Call ``callback`` with every tile-switch event (undeclare the returned subscriber
        or close the client to stop)."""
        def on_sample(sample: zenoh.Sample) -> None:
            callback(codec.decode(TileEvent, sample.payload.to_bytes()))
        return self.session.declare_subscriber(self.key("events", "tile"), on_sample)

    def servers(self, timeout: float | None = None) -> list[str]:
        """Ids of the live servers of this map (liveliness tokens)."""
        key = self.key("@server", "*")
        return [last_chunk(str(r.ok.key_expr))
                for r in self.session.liveliness().get(key, timeout=timeout or self.timeout)
                if r.ok is not None]

    # -- publishing -----------------------------------------------------------------------
    def _publisher(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            # BLOCK: the default DROP loses large messages under load
            # (docs/architecture.md#5-the-wire).
            pub = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK,
                encoding=zenoh.Encoding(encodings.MSGPACK))  # ISMs and poses are msgpack
            self._publishers[key] = pub
        return pub

    def publish_ism(self, key: str, data: npt.NDArray[Any], *, resolution: float,
                    origin: Pose2D | None = None, encoding: str | None = None,
                    layer: str | None = None, frame: str = "map", stamp: float | None = None,
                    robot: str | None = None, wait: bool = False,
                    timeout: float | None = None) -> IsmMessage:
        """Publish an ISM grid on ``key`` (e.g. ``ism/robot1/laser/obstacle``).

        ``encoding`` defaults from the dtype: uint8 -> prob_u8, int8 -> occupancy_i8,
        float -> prob_f32.  ``stamp``: Unix time in seconds, default now (a layer that forgets
        weighs an ISM by its age).  A grid that is not 2-D, values that do not fit the
        encoding or an invalid field raise :class:`InvalidIsmError` (nothing is sent).

        Each ISM carries an id (its Zenoh attachment) so the server can say what became of
        it: with ``wait=True`` this returns once the ISM is fused (a query then sees it) and
        raises :class:`IsmNotFusedError` with the server's reason when it was rejected, or
        :class:`QueryTimeoutError` after ``timeout`` (default 15 s); without, see
        :meth:`wait_fused`.
        """
        msg = build_ism(data, resolution=resolution, origin=origin, encoding=encoding,
                        layer=layer, frame=frame, stamp=stamp, robot=robot)
        ism_id = f"{self._id_prefix}-{next(self._ids)}"
        self._pending[ism_id] = key
        sent = msg if self.compression is None else msg.compressed()
        self.offline.send(HeldIsm(key, codec.encode(sent), ism_id))
        if wait:
            self.wait_fused([ism_id], timeout)
        return msg

    def flush_offline(self, timeout: float = 0.0) -> int:
        """Send the held ISMs whose key has a route again, waiting up to ``timeout`` seconds
        for the rest; returns how many are still held."""
        return self.offline.flush(timeout)

    def settle_offline(self, timeout: float = 2.0) -> int:
        """Ask the server, within ``timeout`` seconds, about each key's last put and the ISMs
        put just before a route was lost; those it never received go through the offline
        policy (each key's newest is sent again, older ones dropped as superseded).  Returns
        how many are lost for good (``lost_in_flight`` in :meth:`offline_stats`)."""
        return self.offline.settle(lambda ism_id, budget: self.ack(ism_id, budget).status,
                                   timeout)

    def offline_stats(self) -> OfflineStats:
        """ISMs offered, sent, held for a route and dropped by the offline policy."""
        return self.offline.buffer.stats()

    def _forget(self, ism_ids: list[str]) -> None:
        for ism_id in ism_ids:  # dropped by the offline policy: wait_fused says so
            self._dropped[ism_id] = self._pending.pop(ism_id, "")
        while len(self._dropped) > 4096:
            self._dropped.pop(next(iter(self._dropped)))

    @property
    def last_ism_id(self) -> str | None:
        """The id of the last ISM this client published and has not yet waited for."""
        return next(reversed(self._pending), None)

    def ack(self, ism_id: str, timeout: float | None = None) -> IsmAck:
        """What became of the ISM published with ``ism_id`` (queued, fused, rejected or
        unknown), asked of the server now."""
        return codec.decode(IsmAck, self.get_raw(self.key("ack"), {"id": ism_id}, timeout))

    def wait_fused(self, ism_ids: Iterable[str] | None = None,
                   timeout: float | None = None) -> list[IsmAck]:
        """Wait until the server has fused each ISM (default: every ISM this client published
        and has not waited for yet); returns their acknowledgements.

        Raises :class:`IsmNotFusedError` (code and reason from the server) for the first one
        it rejected and :class:`QueryTimeoutError` when one is still queued or unknown after
        ``timeout`` seconds (default 15 s) in all."""
        ids = list(self._pending) if ism_ids is None else list(ism_ids)
        budget = timeout or WAIT_FUSED_TIMEOUT_S
        deadline = time.monotonic() + budget
        done: dict[str, IsmAck] = {}
        pause = 0.002
        while True:
            self.offline.flush()
            for ism_id in ids:
                if ism_id in done:
                    continue
                if ism_id in self._dropped:
                    raise IsmNotFusedError("dropped_offline", "dropped by the client's offline "
                                           "policy (no route to a server: only the latest "
                                           "ISM of a key is kept)", self._dropped.pop(ism_id))
                ack = self.ack(ism_id, timeout=max(0.5, min(self.timeout,
                                                            deadline - time.monotonic())))
                if ack.status == "rejected":
                    key = self._pending.pop(ism_id, ack.key)
                    raise IsmNotFusedError(ack.code or "unknown", ack.message, key)
                if ack.status == "fused":
                    self._pending.pop(ism_id, None)
                    done[ism_id] = ack
            if len(done) == len(ids):
                return [done[i] for i in ids]
            if time.monotonic() >= deadline:
                waiting = [i for i in ids if i not in done]
                raise QueryTimeoutError(
                    f"{len(waiting)} ISM(s) not fused within {budget:g} s (first: "
                    f"{self._pending.get(waiting[0], waiting[0])}): is a server of map "
                    f"{self.map_name!r} subscribed to this key?")
            time.sleep(pause)
            pause = min(pause * 2, 0.1)

    def subscribe_rejections(self, callback: Callable[[str, RejectionReport], None],
                             robot: str = "*") -> zenoh.Subscriber:
        """Call ``callback(robot, report)`` for each ISM the server rejects (of ``robot``,
        default every robot): ``report.code``, ``.message``, ``.key``, ``.id``."""
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                report = codec.decode(RejectionReport, sample.payload.to_bytes())
            except codec.DecodeError:
                return
            callback(last_chunk(str(sample.key_expr)), report)
        return self.session.declare_subscriber(self.key("rejections", robot), on_sample)

    def publish_raw(self, key: str, payload: bytes) -> None:
        self._publisher(key).put(payload)

    def publish_pose(self, robot: str, x: float, y: float, yaw: float = 0.0, *,
                     stamp: float = 0.0, frame: str = "map", key_prefix: str = "pose",
                     fix: GeodeticFix | None = None) -> None:
        msg = PoseMessage(robot=robot, frame=frame, stamp=stamp, x=x, y=y, yaw=yaw, fix=fix)
        self._publisher(pose_key(key_prefix, robot)).put(codec.encode(msg))

    # -- watching the fleet (viewer, dashboards) -----------------------------------------
    def subscribe_poses(self, callback: Callable[[str, PoseMessage], None],
                        key_expr: str = "pose/**") -> zenoh.Subscriber:
        """Call ``callback(robot, pose)`` with every valid robot pose on ``key_expr`` (the
        robot is the message's, else the key's last part); invalid payloads are skipped."""
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = codec.decode(PoseMessage, sample.payload.to_bytes())
            except codec.DecodeError:
                return
            callback(msg.robot or str(sample.key_expr).rsplit("/", 1)[-1], msg)
        return self.session.declare_subscriber(key_expr, on_sample)

    def subscribe_ism_footprints(self, callback: Callable[[IsmFootprint], None],
                                 key_expr: str = "ism/**") -> zenoh.Subscriber:
        """Call ``callback`` with where each ISM on ``key_expr`` lies (its header only: the
        cells are neither validated nor kept); payloads without a usable header are skipped."""
        def on_sample(sample: zenoh.Sample) -> None:
            footprint = ism_footprint(str(sample.key_expr), sample.payload.to_bytes())
            if footprint is not None:
                callback(footprint)
        return self.session.declare_subscriber(key_expr, on_sample)


def _param(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v)
    if isinstance(v, float) and math.isfinite(v):
        return repr(v)
    return str(v)
