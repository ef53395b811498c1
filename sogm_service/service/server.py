"""The map server daemon: Zenoh glue around the pure core (DESIGN.md sections 2-4).

Threads and why:

* Zenoh's own callback threads receive ISMs and only enqueue the raw payload, so the network
  side is never slowed by decoding or fusion.
* One ingestion worker decodes, validates and fuses ISMs in arrival order.  The queue is
  bounded: with the ``lossless`` policy a full queue blocks the subscriber callback, which
  pushes back through Zenoh to publishers that use congestion control BLOCK; with ``latest``
  only the newest ISM per key waits and the replaced ones are counted as dropped.
* Queries run on Zenoh's query threads and take the map lock only for the sampling itself, so
  they wait at most for the one ISM being fused, never for the backlog.
* Persistence (tile store, checkpoints, eviction) lives in :mod:`sogm_service.service.persistence`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from pydantic import BaseModel

from sogm_service.core.tiles import TiledMap
from sogm_service.service import pipeline as ingest
from sogm_service.service import queries
from sogm_service.service.config import ServiceConfig
from sogm_service.service.matcher import Matcher
from sogm_service.service.persistence import Persistence
from sogm_service.service.session import open_session
from sogm_service.service.stats import Stats
from sogm_service.wire import codec
from sogm_service.wire.messages import (
    ErrorReply,
    FusedRequest,
    InfoReply,
    IsmMessage,
    PoseMessage,
    StatsReply,
    SubmapRequest,
    SupercellRequest,
)

log = logging.getLogger("sogm_service.service.server")


@dataclass(frozen=True, slots=True)
class _Item:
    source: int
    key: str
    payload: bytes


class IngestQueue:
    """Bounded hand-off from Zenoh callbacks to the worker, ``lossless`` or ``latest``."""

    def __init__(self, size: int, policy: str, stats: Stats) -> None:
        self.policy = policy
        self._stats = stats
        self._fifo: queue.Queue[_Item | None] = queue.Queue(maxsize=size)
        self._latest: dict[str, _Item] = {}
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: _Item) -> bool:
        """Enqueue; ``lossless`` blocks while full.  False once the queue is closed."""
        if self._closed:
            return False
        if self.policy == "lossless":
            while not self._closed:
                try:
                    self._fifo.put(item, timeout=0.2)
                    return True
                except queue.Full:
                    continue
            return False
        with self._cond:
            if item.key in self._latest:
                self._stats.count("isms_dropped_latest")
            self._latest[item.key] = item
            self._cond.notify()
        return True

    def get(self, timeout: float) -> _Item | None:
        if self.policy == "lossless":
            try:
                return self._fifo.get(timeout=timeout)
            except queue.Empty:
                return None
        with self._cond:
            if not self._latest and not self._cond.wait_for(lambda: bool(self._latest),
                                                            timeout):
                return None
            key = next(iter(self._latest))
            return self._latest.pop(key)

    def depth(self) -> int:
        return self._fifo.qsize() if self.policy == "lossless" else len(self._latest)

    def close(self) -> None:
        """Refuse new items; what is queued stays for the worker to finish."""
        self._closed = True


class _RateLimitedLog:
    """One log line per rejection, at most one a second per reason (counts the rest)."""

    def __init__(self) -> None:
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, reason: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= 1.0:
            extra = self._suppressed.pop(reason, 0)
            more = f" ({extra} more of this reason suppressed)" if extra else ""
            log.warning("rejected ISM [%s]: %s%s", reason, text, more)
            self._last[reason] = now
        else:
            self._suppressed[reason] = self._suppressed.get(reason, 0) + 1


class MapServer:
    """One map, served over Zenoh.  ``start()``, then ``stop()`` (or use as a context manager)."""

    def __init__(self, config: ServiceConfig, session: zenoh.Session | None = None) -> None:
        self.config = config
        self.stats = Stats()
        self.lock = threading.RLock()
        self.persistence = Persistence(config, self.stats)
        self.matcher = Matcher(config, self.stats)
        self.map = TiledMap(config.map.name, config.map.frame, self.persistence.lattice,
                            config.map.eps0, loader=self.persistence.load)
        self._owns_session = session is None
        self._session = session
        self._queue = IngestQueue(config.limits.queue_size, config.limits.queue_policy,
                                  self.stats)
        self._declared: list[Any] = []
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._reject_log = _RateLimitedLog()
        self.server_id = ""

    # -- lifecycle ------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        assert self._session is not None, "server not started"
        return self._session

    def start(self) -> MapServer:
        self.persistence.open(self.map)
        if self._session is None:
            self._session = open_session(self.config.zenoh)
        self.server_id = str(self._session.info.zid())
        self.matcher.attach(self._session)
        self._worker = threading.Thread(target=self._work, name="sogm-ingest", daemon=True)
        self._worker.start()
        self._declare()
        self.persistence.start(self.map, self.lock)
        log.info("serving map %r (frame %s, %.3f m) as %s; ISMs on %s", self.config.map.name,
                 self.config.map.frame, self.config.map.resolution, self.server_id,
                 [s.key_expr for s in self.config.ism])
        return self

    def _declare(self) -> None:
        s = self.session
        if self.config.tiles.replicate_on_start:  # before anything can be asked of this server
            self.persistence.replicate(s)
        for idx, source in enumerate(self.config.ism):
            self._declared.append(s.declare_subscriber(
                source.key_expr, self._on_ism_callback(idx)))
        for key in self.config.pose_keys:
            self._declared.append(s.declare_subscriber(key, self._on_pose))
        handlers: dict[str, Callable[[zenoh.Query], BaseModel | bytes | None]] = {
            "submap": self._on_submap, "fused": self._on_fused,
            "supercells": self._on_supercells,
            "info": self._on_info, "stats": self._on_stats,
        }
        for name, handler in handlers.items():
            self._declared.append(s.declare_queryable(self.config.key(name),
                                                      self._guarded(name, handler)))
        self._declared.extend(self.persistence.declare(s, self._guarded))
        self._declared.append(
            s.liveliness().declare_token(self.config.key("@server", self.server_id)))

    def stop(self, timeout: float = 10.0) -> None:
        """Stop accepting work, finish what is queued, flush the store, close the session."""
        self._queue.close()
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:  # already gone with a closing session: nothing to undo
                log.debug("undeclare failed", exc_info=True)
        self._declared.clear()
        self._stop.set()
        if self._worker is not None:
            self._worker.join(timeout)
        self.persistence.close(self.map, self.lock, timeout)
        if self._owns_session and self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> MapServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- ingestion ------------------------------------------------------------------------
    def _on_ism_callback(self, source: int) -> Callable[[zenoh.Sample], None]:
        limit = self.config.limits.max_payload_bytes

        def on_ism(sample: zenoh.Sample) -> None:
            self.stats.count("isms_received")
            payload = sample.payload.to_bytes()
            if len(payload) > limit:  # refused before it can occupy the queue
                self._reject("too_large", f"{sample.key_expr}: payload of {len(payload)} "
                                          f"bytes exceeds {limit}")
                return
            self._queue.put(_Item(source, str(sample.key_expr), payload))
        return on_ism

    def _work(self) -> None:
        while True:
            item = self._queue.get(timeout=0.1)
            if item is None:
                if self._stop.is_set() and self._queue.depth() == 0:
                    return
                continue
            self._handle_ism(item)

    def _handle_ism(self, item: _Item) -> None:
        source = self.config.ism[item.source]
        started = time.perf_counter()
        try:
            msg = codec.decode(IsmMessage, item.payload,
                               context={"max_cells": self.config.limits.max_ism_cells})
            layer = ingest.layer_name(msg, item.key, source.key_expr)
            self.fuse(msg, item.key, layer, item.source)
        except (codec.DecodeError, ingest.IsmRejectedError) as exc:
            self._reject(str(getattr(exc, "code", "invalid")), f"{item.key}: {exc}")
            return
        except Exception as exc:  # never let one ISM kill the worker
            log.exception("internal error on ISM from %s", item.key)
            self._reject("internal_error", f"{item.key}: {type(exc).__name__}: {exc}")
            return
        self.stats.fused()
        self.stats.latency("fuse", time.perf_counter() - started)

    def fuse(self, msg: IsmMessage, key: str, layer: str, source: int) -> None:
        """Fuse one validated ISM: extent check, optional scan matching, Eq. 1."""
        inc, geometry = ingest.prepare(self.map, msg)
        ingest.check_extent(self.map, geometry, self.config.limits.max_ism_tiles)
        if self.matcher.enabled(source):
            inc, geometry = self.matcher.place(self.map, self.lock, msg, key, layer, source,
                                               inc, geometry)
        with self.lock:
            touched = self.map.fuse(layer, inc, geometry, self.config.ism[source].interp,
                                    msg.stamp)
        centre = geometry.cell_to_world()[:2] @ np.array(
            [(geometry.width - 1) / 2, (geometry.height - 1) / 2, 1.0])
        self.persistence.touched(touched, msg.robot, (float(centre[0]), float(centre[1])),
                                 msg.stamp)

    def _reject(self, reason: str, text: str) -> None:
        self.stats.reject(reason)
        self._reject_log.warn(reason, text)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            msg = codec.decode(PoseMessage, sample.payload.to_bytes())
        except codec.DecodeError as exc:
            self.stats.count(f"poses_rejected_{exc.code}")
            return
        robot = msg.robot or str(sample.key_expr).rsplit("/", 1)[-1]
        self.stats.count("poses_received")
        self.persistence.robot_pose(robot, msg.x, msg.y, msg.stamp)

    # -- queries --------------------------------------------------------------------------
    def _guarded(self, name: str,
                 handler: Callable[[zenoh.Query], BaseModel | bytes | None]
                 ) -> Callable[[zenoh.Query], None]:
        def on_query(q: zenoh.Query) -> None:
            started = time.perf_counter()
            self.stats.count(f"queries_{name}")
            try:
                result = handler(q)
                if result is not None:
                    payload = result if isinstance(result, bytes) else codec.encode(result)
                    q.reply(q.key_expr, payload)
            except queries.QueryError as exc:
                self.stats.count(f"query_errors_{exc.code}")
                q.reply_err(codec.encode(ErrorReply(code=exc.code, message=exc.message,
                                                    parameter=exc.parameter)))
            except Exception as exc:
                log.exception("internal error answering %s", q.selector)
                self.stats.count("query_errors_internal")
                q.reply_err(codec.encode(ErrorReply(code="internal_error",
                                                    message=f"{type(exc).__name__}: {exc}")))
            self.stats.latency(name, time.perf_counter() - started)
        return on_query

    @staticmethod
    def params(q: zenoh.Query) -> tuple[dict[str, str], bytes | None]:
        body = q.payload.to_bytes() if q.payload is not None else None
        pairs: list[tuple[str, str]] = list(q.selector.parameters)  # type: ignore[call-overload]
        return dict(pairs), body

    def _on_submap(self, q: zenoh.Query) -> BaseModel:
        req = queries.parse_request(SubmapRequest, *self.params(q))
        with self.lock:
            return queries.submap(self.map, req, self.config.limits.max_query_cells, time.time())

    def _on_fused(self, q: zenoh.Query) -> BaseModel:
        req = queries.parse_request(FusedRequest, *self.params(q))
        with self.lock:
            return queries.fused(self.map, req, self.config.limits.max_query_cells, time.time())

    def _on_supercells(self, q: zenoh.Query) -> BaseModel:
        req = queries.parse_request(SupercellRequest, *self.params(q))
        with self.lock:
            window, layers, stack = queries.supercell_input(
                self.map, req, self.config.limits.max_query_cells)
        return queries.supercells(self.map, req, window, layers, stack, time.time())

    def info(self) -> InfoReply:
        with self.lock:
            return InfoReply(
                map=self.map.name, frame=self.map.frame, server_id=self.server_id,
                resolution=self.map.lattice.resolution, tile_size=self.map.tile_size,
                eps0=self.map.eps0, logodds_scale=1000.0, layers=list(self.map.layers),
                tiles=sorted(self.map.known_tiles()), bounds=self.map.bounds(),
                datum=self.config.map.datum)

    def _on_info(self, q: zenoh.Query) -> BaseModel:
        return self.info()

    def stats_reply(self) -> StatsReply:
        counters, rejected = self.stats.snapshot()
        with self.lock:
            extra: dict[str, Any] = {
                "layers": len(self.map.layers),
                "tiles_resident": len(self.map.tiles),
                "tiles_known": len(self.map.known_tiles()),
                "resident_mb": round(self.map.resident_bytes() / 1e6, 3),
            }
        extra.update(self.persistence.stats_extra())
        extra.update(self.matcher.stats_extra())
        return StatsReply(map=self.map.name, server_id=self.server_id,
                          uptime_s=time.monotonic() - self.stats.started, counters=counters,
                          rejected=rejected, queue_depth=self._queue.depth(),
                          isms_per_s=self.stats.isms_per_s(),
                          latency_ms=self.stats.percentiles(), extra=extra)

    def _on_stats(self, q: zenoh.Query) -> BaseModel:
        return self.stats_reply()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until the ingestion queue is empty and the worker idle (tests, demo)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            counters, _ = self.stats.snapshot()
            done = (counters.get("isms_fused", 0) + counters.get("isms_rejected", 0)
                    + counters.get("isms_dropped_latest", 0))
            if self._queue.depth() == 0 and done >= counters.get("isms_received", 0):
                return True
            time.sleep(0.01)
        return False
