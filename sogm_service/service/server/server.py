"""The map server daemon: the Zenoh wiring around the ingestion pipeline and the queries.

Threads and why (architecture, sections 3 and 7: docs/architecture.md#3-the-two-data-paths,
docs/architecture.md#7-queries-never-wait-behind-ingestion):

* Zenoh's own callback threads receive ISMs and only queue the raw payload
  (:mod:`sogm_service.service.server.ingest`), so the network side is never slowed by decoding or
  fusion; one worker runs the :class:`~sogm_service.service.server.pipeline.IngestPipeline` in
  arrival order.
* Fuse workers (:mod:`sogm_service.service.server.fusers`) fuse each ISM over disjoint tiles, so
  ingestion uses several cores and the map stays the same for any number of them.
* Queries run on Zenoh's query threads: request -> sampling -> reply
  (:mod:`sogm_service.service.server.queries`).  Zenoh's receive runtime gets
  ``[limits] rx_threads`` threads, so the ISM links a lossless push-back holds leave others to
  read queries (:func:`~sogm_service.service.server.ingest.reserve_rx_threads`).  They take
  no map-wide lock: a tile is locked only while its block is copied or one ISM's patch is
  added to it (:mod:`sogm_service.core.map.tiles`), so a query never waits for the ingestion
  backlog, nor even for one whole ISM.
* Checkpoints, eviction (:mod:`~sogm_service.service.server.checkpoints`), the fleet's tiles
  (:mod:`~sogm_service.service.server.fleet`) and whole-tile replication
  (:mod:`~sogm_service.service.cluster.replication`) are parts this class wires to the session.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from pydantic import BaseModel

from sogm_service.client.session import open_session
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.cluster.cluster import Cluster
from sogm_service.service.cluster.replication import Replication
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server import queries, tilesync
from sogm_service.service.server.acks import IsmOutcomes, ism_id_of
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.droplayers import LayerDrop
from sogm_service.service.server.fleet import FleetTracker
from sogm_service.service.server.fusers import FuseWorkers
from sogm_service.service.server.ingest import IngestQueue, IngestWorker, reserve_rx_threads
from sogm_service.service.server.matcher import Matcher
from sogm_service.service.server.pipeline import IngestPipeline, IsmItem, check_robot
from sogm_service.service.server.stats import Stats
from sogm_service.wire import codec, encodings
from sogm_service.wire.errors import QueryError, SogmError
from sogm_service.wire.keys import QUERYABLES, last_chunk
from sogm_service.wire.limits import WARMUP_WAIT_S
from sogm_service.wire.messages import ErrorReply, PoseMessage, TileEvent
from sogm_service.wire.queries import (
    FusedRequest,
    InfoReply,
    StatsReply,
    SubmapRequest,
    SupercellRequest,
)

log = logging.getLogger(__name__)

Handler = Callable[[zenoh.Query], queries.Answer | BaseModel | bytes | None]


MSGPACK = zenoh.Encoding(encodings.MSGPACK)
"""Every reply, error reply, event and report the server sends is a msgpack wire model."""
MSGPACK_ZSTD = MSGPACK.with_schema(encodings.ZSTD_SCHEMA)
"""A reply compressed for an asker that wanted it: the msgpack bytes as one zstd frame."""


class MapServer:
    """One map, served over Zenoh.  ``start()``, then ``stop()`` (or use as a context manager)."""

    def __init__(self, config: ServiceConfig, session: zenoh.Session | None = None) -> None:
        self.config = config
        self.keys = config.keys
        self.stats = Stats()
        lattice = TileLattice(config.map.resolution, config.map.tile_size)
        self.fleet = FleetTracker(config, lattice, self.stats)
        self.tiles = Checkpointer(config, self.stats, keep=self.fleet.regions_of_interest)
        self.map = TiledMap(config.map.name, config.map.frame, lattice, config.map.eps0,
                            loader=self.tiles.load)
        self.map.set_forget(config.map.forget)
        self.matcher = Matcher(config, self.stats)
        self.replication = Replication(config, self.map, self.tiles, self.stats)
        self.fusers = FuseWorkers(self.map, config.limits.fuse_workers)
        self.pipeline = IngestPipeline(config, self.map, self.stats, self.matcher, self.fleet,
                                       self.tiles, self.fusers)
        self._queue = IngestQueue(config.limits.queue_size, config.limits.queue_policy,
                                  self.stats)
        self._worker = IngestWorker(self._queue, self.pipeline.handle, self.stats)
        self.cluster: Cluster | None = None
        if config.cluster.enabled:
            self.cluster = Cluster(config, self.map, self.tiles, self.stats, self.fusers,
                                   lambda t: self.wait_idle(t) and self.fusers.drain(t))
            self.pipeline.owns_none = self.cluster.owns_none
        self.outcomes = IsmOutcomes(self.keys, [s.key_expr for s in config.ism])
        self.pipeline.outcomes = self.outcomes
        self.warmed_up = threading.Event()  # the SEVDS kernels are compiled or loaded
        self._warm_up_child: subprocess.Popen[str] | None = None
        self._stopped = threading.Event()
        self._owns_session = session is None
        self._session = session
        self._declared: list[Any] = []
        self._events: zenoh.Publisher | None = None
        self._ros2: Any = None  # a service.ros2.Ros2Link when [ros2] enabled
        self.server_id = ""

    # -- lifecycle ------------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        assert self._session is not None, "server not started"
        return self._session

    def start(self) -> MapServer:
        self.tiles.attach(self.map)
        if self._session is None:  # receive threads first: a push-back must not hold them all
            with reserve_rx_threads(self.config.limits.rx_threads):
                self._session = open_session(self.config.zenoh)
        self.server_id = str(self._session.info.zid())
        self.matcher.attach(self._session)
        self._worker.start()
        self._declare()
        self.fleet.attach(self._publish_event, self.tiles)
        if self.config.ros2.enabled:
            from sogm_service.service.ros2.link import Ros2Link  # the ros2 extra: only when enabled

            self._ros2 = Ros2Link(self.config, self._session, self.map, self._queue, self.fleet,
                                  self.stats, self.pipeline.rejections)
        self.tiles.start()
        session = self._session  # rejection reports go out with their declared encoding
        self.outcomes.attach(lambda key, payload: session.put(key, payload, encoding=MSGPACK))
        # Last: the token says "ready", so a client that waits for it finds every subscriber
        # and queryable declared, the ack queryable included.
        self._declared.append(
            self._session.liveliness().declare_token(self.keys.server_token(self.server_id)))
        self._start_warm_up()
        log.info("serving map %r (frame %s, %.3f m) as %s; ISMs on %s", self.config.map.name,
                 self.config.map.frame, self.config.map.resolution, self.server_id,
                 [s.key_expr for s in self.config.ism])
        return self

    def _declare(self) -> None:
        s = self.session
        if self.config.tiles.replicate_on_start:  # before anything can be asked of this server
            self.replication.replicate(s)
        for idx, source in enumerate(self.config.ism):
            self._declared.append(s.declare_subscriber(source.key_expr, self._on_ism(idx)))
        for key in self.config.pose_keys:
            self._declared.append(s.declare_subscriber(key, self._on_pose))
        handlers: dict[str, Handler] = {
            "submap": self._on_submap, "fused": self._on_fused,
            "supercells": self._on_supercells, "info": lambda q: self.info(),
            "stats": lambda q: self.stats_reply(),
        }
        assert set(handlers) == set(QUERYABLES)
        for name, handler in handlers.items():
            # Complete: this server answers for the whole map (in a cluster it gathers what it
            # does not own), so a client's get (BEST_MATCHING) reaches the nearest server
            # only; an incomplete queryable is asked on every server and each one computes
            # the reply.  ``stats`` is per server: a get reaches them all unless told.
            self._declared.append(s.declare_queryable(self.keys.key(name),
                                                      self._guarded(name, handler),
                                                      complete=name != "stats"))
            if self.cluster is not None:  # and under this member's own key
                self._declared.append(s.declare_queryable(
                    self.keys.member(self.server_id, name), self._guarded(name, handler)))
        self._events = s.declare_publisher(self.keys.tile_events, encoding=MSGPACK,
                                           congestion_control=zenoh.CongestionControl.BLOCK,
                                           reliability=zenoh.Reliability.RELIABLE)
        self._declared.append(self._events)
        self._declared.append(s.declare_queryable(
            self.keys.all_tiles, self._guarded("tiles", self.replication.on_tiles)))
        self._declared.append(s.declare_queryable(self.keys.tiles_changed, self._guarded(
            "tiles_changed", tilesync.TileSync(self.keys, self.map, self.tiles,
                                               self.replication.files.encode,
                                               self.pipeline.admission, self.stats).on_changed)))
        self._declared.append(s.declare_queryable(
            self.keys.robots, self._guarded("robots", lambda q: self.fleet.robots_reply())))
        self._declared.append(s.declare_queryable(self.keys.ack,
                                                  self._guarded("ack", self._on_ack)))
        drop = LayerDrop(self.keys, self.map, self.tiles, self.stats, lambda: self.server_id,
                         clustered=self.cluster is not None)
        self._declared.append(s.declare_queryable(self.keys.all_drops,
                                                  self._guarded("drop", drop.on_query)))
        if self.cluster is not None:  # pulls the tiles it will own before declaring itself
            self.cluster.join(s, self.server_id)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop accepting work, finish what is queued, flush the store, close the session."""
        if self._ros2 is not None:
            self._ros2.close(timeout)
            self._ros2 = None
        self._queue.close()
        self._stopped.set()
        self._end_warm_up()
        if self.cluster is not None:
            self.cluster.close()
        self.outcomes.attach(None)
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:  # already gone with a closing session: nothing to undo
                log.debug("undeclare failed", exc_info=True)
        self._declared.clear()
        self._events = None
        self._worker.stop(timeout)
        self.fusers.close(timeout)
        self.fleet.close(timeout)
        self.tiles.close(timeout)
        if self._owns_session and self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> MapServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- ingestion ------------------------------------------------------------------------
    def _on_ism(self, source: int) -> Callable[[zenoh.Sample], None]:
        limit = self.config.limits.max_payload_bytes

        def on_ism(sample: zenoh.Sample) -> None:
            self.stats.count("isms_received")
            payload = sample.payload.to_bytes()
            key = str(sample.key_expr)
            attachment = sample.attachment
            ism_id = ism_id_of(attachment.to_bytes()) if attachment is not None else None
            self.outcomes.queued(ism_id, key)
            if len(payload) > limit:  # refused before it can occupy the queue
                text = f"payload of {len(payload)} bytes exceeds {limit}"
                self.pipeline.rejections.reject("too_large", f"{key}: {text}")
                self.outcomes.outcome(key, source, ism_id, "too_large", text)
                return
            self._queue.put(IsmItem(source, key, payload, ism_id=ism_id))
        return on_ism

    def _on_pose(self, sample: zenoh.Sample) -> None:
        self.stats.count("poses_received")  # = applied + coalesced + rejected (+ pending)
        try:
            msg = codec.decode(PoseMessage, sample.payload.to_bytes())
            robot = last_chunk(str(sample.key_expr))
            check_robot(msg.robot, robot)
            self.pipeline.admission.check_pose(robot, msg.x, msg.y)
        except SogmError as exc:
            self.stats.count("poses_rejected")
            self.stats.count(f"poses_rejected_{exc.code}")
            return
        self.fleet.submit_pose(robot, msg.x, msg.y, msg.stamp)

    def _publish_event(self, event: TileEvent) -> None:
        if self.cluster is not None and not self.cluster.announces((event.i, event.j)):
            self.stats.count("tile_events_left_to_primary")
            return
        if self._events is not None:
            self._events.put(codec.encode(event))

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until the ingestion queue is empty and the worker idle (tests, demo)."""
        return self._worker.wait_idle(timeout)

    # -- queries --------------------------------------------------------------------------
    def _guarded(self, name: str, handler: Handler) -> Callable[[zenoh.Query], None]:
        """Run ``handler`` and reply; a refusal goes back as an ``ErrorReply`` with its code."""
        def on_query(q: zenoh.Query) -> None:
            started = time.perf_counter()
            self.stats.count(f"queries_{name}")
            try:
                result = handler(q)
                if isinstance(result, queries.Answer):
                    self.stats.count("replies_zstd" if result.compressed else "replies_raw")
                    q.reply(q.key_expr, result.payload(),
                            encoding=MSGPACK_ZSTD if result.compressed else MSGPACK)
                elif result is not None:
                    payload = result if isinstance(result, bytes) else codec.encode(result)
                    q.reply(q.key_expr, payload, encoding=MSGPACK)
            except SogmError as exc:
                self.stats.count(f"query_errors_{exc.code}")
                q.reply_err(codec.encode(ErrorReply(
                    code=exc.code, message=exc.message, parameter=exc.parameter,
                    retry_after_s=getattr(exc, "retry_after_s", None))), encoding=MSGPACK)
            except Exception as exc:
                log.exception("internal error answering %s", q.selector)
                self.stats.count("query_errors_internal")
                q.reply_err(codec.encode(ErrorReply(code="internal_error",
                                                    message=f"{type(exc).__name__}: {exc}")),
                            encoding=MSGPACK)
            self.stats.latency(name, time.perf_counter() - started)
        return on_query

    @staticmethod
    def params(q: zenoh.Query) -> tuple[dict[str, str], bytes | None]:
        body = q.payload.to_bytes() if q.payload is not None else None
        pairs: list[tuple[str, str]] = list(q.selector.parameters)  # type: ignore[call-overload]
        return queries.selector(pairs), body  # a parameter given twice: bad_parameter

    def _on_submap(self, q: zenoh.Query) -> queries.Answer:
        req = queries.parse_request(SubmapRequest, *self.params(q))
        return queries.Answer(req.compression, queries.submap(self.query_map(), req, time.time(),
                                                              admission=self.pipeline.admission))

    def _on_fused(self, q: zenoh.Query) -> queries.Answer:
        req = queries.parse_request(FusedRequest, *self.params(q))
        return queries.Answer(req.compression, queries.fused(self.query_map(), req, time.time(),
                                                             admission=self.pipeline.admission))

    def _on_supercells(self, q: zenoh.Query) -> queries.Answer:
        req = queries.parse_request(SupercellRequest, *self.params(q))
        queries.price_supercells(self.query_map(), req, self.pipeline.admission)  # refuse first
        self.wait_warm(WARMUP_WAIT_S)
        with self.pipeline.admission.heavy("supercells"):  # or busy, with a retry hint
            window, layers, stack = queries.supercell_input(
                self.query_map(), req, admission=self.pipeline.admission)
            graph = queries.supercells(self.map, req, window, layers, stack, time.time())
        return queries.Answer(req.compression, graph)

    def info(self) -> InfoReply:
        tiled = self.map
        tiles = self.pipeline.admission.reportable_tiles(self.all_tiles())
        return InfoReply(
            map=tiled.name, frame=tiled.frame, server_id=self.server_id,
            resolution=tiled.lattice.resolution, tile_size=tiled.tile_size,
            eps0=tiled.eps0, logodds_scale=1000.0, layers=list(tiled.layers),
            tiles=tiles, bounds=self.pipeline.admission.bounds_of(tiles),
            datum=self.config.map.datum)

    def stats_reply(self) -> StatsReply:
        counters, rejected = self.stats.snapshot()
        extra: dict[str, Any] = {
            "layers": len(self.map.layers),
            "tiles_resident": len(self.map.tiles),
            "tiles_known": len(self.map.known_tiles()),
            "resident_mb": round(self.map.resident_bytes() / 1e6, 3),
            "reserved_mb": round(self.pipeline.admission.reserved_bytes / 1e6, 3),
            # The map's clock (the latest ISM stamp): decaying layers read as they are then.
            "map_time": self.map.now() if math.isfinite(self.map.now()) else None,
            "fuse_workers": self.fusers.workers,
            "rx_waiting_max": self._queue.waiting_max,
            "kernels_ready": self.warmed_up.is_set(),
        }
        extra["robots"] = self.fleet.robot_count()
        extra.update(self.tiles.stats_extra())
        extra.update(self.matcher.stats_extra())
        if self._ros2 is not None:
            extra.update(self._ros2.stats_extra())
        if self.cluster is not None:
            extra.update(self.cluster.stats_extra())
        return StatsReply(map=self.config.map.name, server_id=self.server_id,
                          uptime_s=time.monotonic() - self.stats.started, counters=counters,
                          rejected=rejected, queue_depth=self._queue.depth(),
                          isms_per_s=self.stats.isms_per_s(),
                          latency_ms=self.stats.percentiles(), extra=extra)

    # -- cluster (sogm_service.service.cluster) ---------------------------------------
    def query_map(self) -> TiledMap:
        """The map a window query reads: this server's, or in a cluster the tiles it serves
        and its peers' for the rest."""
        return self.map if self.cluster is None else self.cluster.query_map()

    def all_tiles(self) -> set[tuple[int, int]]:
        """Every tile of the map: in a cluster, every member's."""
        return self.map.known_tiles() if self.cluster is None else self.cluster.all_tiles()

    # -- publishers hear back, and the first supercells query -----------------------------
    def _on_ack(self, q: zenoh.Query) -> BaseModel:
        params, _ = self.params(q)
        ism_id = params.get("id", "")
        if ism_id_of(ism_id.encode("utf-8", "replace")) is None:
            raise QueryError("bad_parameter", "id must be an ISM id (1-64 characters of "
                                              "[A-Za-z0-9_.-])", "id")
        return self.outcomes.lookup(ism_id)

    def _start_warm_up(self) -> None:
        """Compile the SEVDS kernels into numba's on-disk cache in a child process, so the
        first supercells query only loads them (0.3-0.5 s) instead of compiling (7 s cold on a
        busy 2-core machine).  A child, not a thread: numba and LLVM cost this process ~110 MB
        of RSS only once a supercells query actually needs them."""
        if self.warmed_up.is_set():
            return

        def run() -> None:
            started = time.perf_counter()
            code = "from sogm_service.core.sevds.segment import warm_up; warm_up()"
            try:
                child = self._warm_up_child = subprocess.Popen(
                    [sys.executable, "-c", code], stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE, text=True)
                if self._stopped.is_set():  # stop() ran while it was starting
                    child.terminate()
                try:
                    _, stderr = child.communicate(timeout=600)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.communicate()
                    raise
                if self._stopped.is_set():  # ended by stop(): nothing worth saying
                    return
                if child.returncode == 0:
                    log.info("supercell kernels compiled into the cache in %.1f s",
                             time.perf_counter() - started)
                else:  # the first query will compile (and report) instead
                    log.warning("warming up the supercell kernels failed: %s",
                                stderr.strip().splitlines()[-1:] or child.returncode)
            except (OSError, subprocess.SubprocessError) as exc:
                log.warning("warming up the supercell kernels failed: %s", exc)
            finally:
                self.warmed_up.set()
        threading.Thread(target=run, name="sogm-warm-up", daemon=True).start()

    def _end_warm_up(self) -> None:
        """A server stopped within seconds of starting (a replay with no scans, a test) leaves
        no compiling child behind; the kernels then compile on a later start."""
        child = self._warm_up_child
        if child is not None and child.poll() is None:
            child.terminate()
            try:
                child.wait(10)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait(5)

    def wait_warm(self, budget_s: float) -> None:
        """Wait up to ``budget_s`` for the warm-up; refuse with ``warming_up`` after that."""
        if not self.warmed_up.wait(budget_s):
            raise QueryError("warming_up", "the supercell kernels are still being compiled "
                                           "(first start after an install); retry in a few "
                                           "seconds")
