"""The viewer's one Zenoh client of the map server, shared by every browser connected to it.

One thread keeps the connection: it opens a :class:`~sogm_service.client.mapclient.MapClient`
(retrying while the map server is away), subscribes to tile events, robot poses and ISM
footprints, and polls ``info`` and ``stats`` every ``poll_s``.  Zenoh's client mode reconnects
by itself when the server comes back on the same endpoint; if it has not after
``reopen_after`` failed polls the session is closed and opened anew.

What arrives from Zenoh is only recorded here (latest pose per robot, bounded deques of events
and footprints); the web side takes it with :meth:`MapHub.drain` on its own schedule, so no
Zenoh callback ever waits for a browser.

Tiles are rendered on demand (:meth:`MapHub.tile`, called from a small thread pool) and cached
by display tile and picture, shared by every browser.  A tile is asked of the map server again
only when the versions of the map tiles under it moved (:meth:`MapHub.versions`, one
``tiles/changed`` check a round, :mod:`.versions`), or, where versions cannot be checked, at
most once per ``max_age``; it is re-encoded only when its cells changed (a digest of the reply).
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.adapters.ros2.filters import FilterSpec
from sogm_service.apps.render import UNKNOWN_HEX, palette_hex
from sogm_service.apps.viewer.pictures import fetch, render
from sogm_service.apps.viewer.tiles import Lattice, TileSpec
from sogm_service.apps.viewer.versions import Bounds, Source, VersionBook
from sogm_service.client.isms import IsmFootprint
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import loopback_settings, open_session
from sogm_service.core import logodds
from sogm_service.core.geodesy import LocalTangentPlane
from sogm_service.core.sevds.supercells import FREE, node_evidence
from sogm_service.service.config import ZenohSettings
from sogm_service.wire.errors import ClientError
from sogm_service.wire.messages import PoseMessage, TileEvent
from sogm_service.wire.queries import InfoReply, StatsReply

log = logging.getLogger("sogm_service.apps.viewer")

MAX_ROBOTS = 1000
"""Robots whose last pose is kept (the least recently seen are forgotten beyond this)."""
MAX_INFO_TILES = 20000
"""Known lattice tiles listed to the page (beyond this the page draws no tile outlines)."""
HISTORY = 120
"""Stats samples kept for the charts (two minutes at the default poll)."""


@dataclass(frozen=True)
class HubSettings:
    endpoint: str | None = "tcp/127.0.0.1:7447"
    map_name: str = "default"
    prefix: str = "sogm"
    zenoh_config: Path | None = None
    pose_key: str = "pose/**"
    ism_key: str | None = "ism/**"
    poll_s: float = 1.0
    query_timeout_s: float = 2.0
    supercells_timeout_s: float = 30.0  # the first SEVDS call of a server loads its kernels
    reopen_after: int = 10
    cache_tiles: int = 1024
    filters: FilterSpec = field(default_factory=FilterSpec)  # the keepout and speed overlays

    def zenoh_settings(self) -> ZenohSettings:
        """Client mode to ``endpoint`` (loopback, multicast off), or the given Zenoh config
        file as it is (the secure set-up: its mode, TLS, certificates and endpoints)."""
        if self.zenoh_config is not None:
            return ZenohSettings(config_file=self.zenoh_config)
        return loopback_settings(connect=self.endpoint, mode="client")


@dataclass
class CachedTile:
    digest: str
    png: bytes
    fetched: float
    source: Source | None = None  # the map-tile versions it was drawn from, when known


@dataclass
class Updates:
    """What changed since the last :meth:`MapHub.drain`."""

    status: dict[str, Any] | None = None
    info: dict[str, Any] | None = None
    poses: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    footprints: list[dict[str, Any]] = field(default_factory=list)
    stats: dict[str, Any] | None = None

    def __bool__(self) -> bool:
        return bool(self.status or self.info or self.poses or self.events or self.footprints
                    or self.stats)


class MapHub:
    """The Zenoh side of the viewer.  ``start()``, then ``close()``."""

    def __init__(self, settings: HubSettings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._client: MapClient | None = None
        self._subs: list[Any] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._tile_locks = [threading.Lock() for _ in range(32)]
        self._cache: OrderedDict[str, CachedTile] = OrderedDict()
        self.book = VersionBook()
        # state, under _lock
        self.connected = False
        self.error: str | None = "connecting"
        self.info: InfoReply | None = None
        self.robots: dict[str, dict[str, Any]] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=100)
        self.stats_history: deque[dict[str, Any]] = deque(maxlen=HISTORY)
        self._pending = Updates()
        self._pending_poses: dict[str, dict[str, Any]] = {}
        self._pending_footprints: deque[dict[str, Any]] = deque(maxlen=64)
        self._pending_events: deque[dict[str, Any]] = deque(maxlen=100)
        self._last_rejected: dict[str, int] = {}
        self.queries = 0
        self.query_failures = 0
        self._warned = False

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> MapHub:
        self._thread = threading.Thread(target=self._run, name="viewer-hub", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
        self._close_client()

    def _open_client(self) -> MapClient:
        s = self.settings
        client = MapClient(open_session(s.zenoh_settings()), s.map_name, s.prefix,
                           s.query_timeout_s, owns_session=True)
        try:
            subs = [client.subscribe_tile_events(self._on_event),
                    client.subscribe_poses(self._on_pose, s.pose_key)]
            if s.ism_key:
                subs.append(client.subscribe_ism_footprints(self._on_footprint, s.ism_key))
        except Exception:
            client.close()
            raise
        with self._lock:
            self._client, self._subs = client, subs
        return client

    def _close_client(self) -> None:
        with self._lock:
            client, subs = self._client, self._subs
            self._client, self._subs = None, []
        for sub in subs:
            try:
                sub.undeclare()
            except Exception:  # the session may already be gone
                log.debug("undeclare failed", exc_info=True)
        if client is not None:
            client.close()

    def client(self) -> MapClient | None:
        with self._lock:
            return self._client if self.connected else None

    # -- the connection thread ------------------------------------------------------------
    def _run(self) -> None:
        failures = 0
        while not self._stop.is_set():
            if self._client is None:
                try:
                    self._open_client()
                    log.info("viewer: session open towards %s", self.settings.endpoint)
                except Exception as exc:  # zenoh.ZError when nothing listens yet
                    self._set_status(False, f"cannot reach the map server: {exc}")
                    self._stop.wait(1.0)
                    continue
            try:
                self._poll()
                failures = 0
            except Exception as exc:  # ClientError, or a closed session's error
                failures += 1
                self._set_status(False, f"the map server does not answer ({exc})")
                if failures >= self.settings.reopen_after:
                    log.info("viewer: reopening the session after %d failed polls", failures)
                    self._close_client()
                    failures = 0
            self._stop.wait(self.settings.poll_s)

    def _poll(self) -> None:
        client = self._client
        if client is None:
            return
        info = client.info()
        stats = client.stats()
        self._set_status(True, None)
        with self._lock:
            old = self.info
            changed = old is None or (old.layers, old.tiles, old.bounds, old.server_id) != \
                (info.layers, info.tiles, info.bounds, info.server_id)
            if old is not None and old.server_id != info.server_id:
                self._cache.clear()  # another server process: nothing cached is its
                self.book.clear()
                self._last_rejected = {}
            self.info = info
            if changed:
                self._pending.info = self._info_message(info)
            sample = self._stats_sample(stats)
            self.stats_history.append(sample)
            self._pending.stats = sample

    def _set_status(self, connected: bool, error: str | None) -> None:
        with self._lock:
            if connected == self.connected and error == self.error:
                return
            was = self.connected
            self.connected, self.error = connected, error
            self._pending.status = self._status_message()
        if connected and not was:
            log.info("viewer: map %r answers at %s", self.settings.map_name,
                     self.settings.endpoint)
            self._warned = False
        elif not connected and not self._warned:  # once per outage, not once per poll
            log.warning("viewer: %s", error)
            self._warned = True

    def _status_message(self) -> dict[str, Any]:
        return {"type": "status", "connected": self.connected, "error": self.error,
                "endpoint": self.settings.endpoint, "map": self.settings.map_name}

    def _stats_sample(self, stats: StatsReply) -> dict[str, Any]:
        rejected = {}
        for reason, n in stats.rejected.items():
            before = self._last_rejected.get(reason, 0)
            rejected[reason] = n - before if n >= before else n  # a restarted server
        self._last_rejected = dict(stats.rejected)
        latency = {name: round(v["p50"], 3) for name, v in stats.latency_ms.items()
                   if name in ("submap", "fused", "supercells")}
        return {"type": "stats", "t": time.time(), "isms_per_s": round(stats.isms_per_s, 3),
                "queue_depth": stats.queue_depth, "rejected": rejected,
                "rejected_total": sum(stats.rejected.values()), "latency_p50_ms": latency,
                "isms_fused": stats.counters.get("isms_fused", 0)}

    def _info_message(self, info: InfoReply) -> dict[str, Any]:
        geo = None
        if info.datum is not None:
            plane = LocalTangentPlane(info.datum)
            east, north = plane.to_geodetic(1.0, 0.0), plane.to_geodetic(0.0, 1.0)
            geo = {"latitude": info.datum.latitude, "longitude": info.datum.longitude,
                   "deg_lat_per_m": north.latitude - info.datum.latitude,
                   "deg_lon_per_m": east.longitude - info.datum.longitude}
        tiles = [list(t) for t in info.tiles] if len(info.tiles) <= MAX_INFO_TILES else []
        return {"type": "info", "map": info.map, "frame": info.frame,
                "server_id": info.server_id, "resolution": info.resolution,
                "tile_size": info.tile_size, "layers": list(info.layers),
                "palette": palette_hex(len(info.layers)), "unknown": UNKNOWN_HEX,
                "tiles": tiles, "tile_count": len(info.tiles), "bounds": info.bounds,
                "geo": geo}

    # -- Zenoh callbacks: record only -------------------------------------------------------
    def _on_event(self, event: TileEvent) -> None:
        msg = {"type": "tile_event", **event.model_dump(mode="json"), "received": time.time()}
        with self._lock:
            self.events.append(msg)
            self._pending_events.append(msg)

    def _on_pose(self, robot: str, pose: PoseMessage) -> None:
        msg = {"type": "pose", "robot": robot, "frame": pose.frame, "x": pose.x, "y": pose.y,
               "yaw": pose.yaw, "stamp": pose.stamp}
        with self._lock:
            self.robots.pop(robot, None)
            self.robots[robot] = msg  # most recently seen last
            while len(self.robots) > MAX_ROBOTS:
                del self.robots[next(iter(self.robots))]
            self._pending_poses[robot] = msg
            while len(self._pending_poses) > MAX_ROBOTS:
                del self._pending_poses[next(iter(self._pending_poses))]

    def _on_footprint(self, fp: IsmFootprint) -> None:
        msg = {"type": "footprint", "key": fp.key, "robot": fp.robot, "layer": fp.layer,
               "corners": [list(c) for c in fp.corners]}
        with self._lock:
            self._pending_footprints.append(msg)

    # -- what the web side reads ----------------------------------------------------------
    def drain(self) -> Updates:
        """Everything that changed since the last call (non-blocking)."""
        with self._lock:
            out, self._pending = self._pending, Updates()
            out.poses = list(self._pending_poses.values())
            out.events = list(self._pending_events)
            out.footprints = list(self._pending_footprints)
            self._pending_poses.clear()
            self._pending_events.clear()
            self._pending_footprints.clear()
        return out

    def hello(self) -> dict[str, Any]:
        """The whole state a newly connected page starts from."""
        with self._lock:
            info = self._info_message(self.info) if self.info is not None else None
            return {"type": "hello", "status": self._status_message(), "info": info,
                    "robots": list(self.robots.values()), "events": list(self.events),
                    "stats": list(self.stats_history)}

    def lattice(self) -> Lattice | None:
        with self._lock:
            if self.info is None:
                return None
            return Lattice(self.info.resolution, self.info.tile_size)

    def known_tiles(self) -> list[tuple[int, int]]:
        with self._lock:
            return [] if self.info is None else list(self.info.tiles)

    def layers(self) -> list[str]:
        with self._lock:
            return [] if self.info is None else list(self.info.layers)

    # -- queries (blocking; called from the web side's thread pool) ------------------------
    def versions(self, bounds: Bounds, max_age: float) -> dict[tuple[int, int], int] | None:
        """The current versions of the known map tiles within ``bounds`` (one ``tiles/changed``
        check, shared by every page for ``max_age`` s), or None: ask every tile instead."""
        client, info = self.client(), self.info
        if client is None or info is None:
            return None
        try:
            return self.book.versions(client, info, bounds, max_age,
                                      self.settings.query_timeout_s)
        except Exception as exc:  # ClientError (refused, timed out) or a closed session
            log.debug("tiles/changed %s: %s: %s", bounds, type(exc).__name__, exc)
            return None

    def tile(self, spec: TileSpec, max_age: float,
             source: Source | None = None) -> CachedTile | None:
        """The picture of one display tile; ``None`` when it cannot be had now.  With the
        ``source`` versions it is drawn from, the cached picture of the same versions is
        current whatever its age; without, the cache serves it for ``max_age`` seconds."""
        key = spec.key
        with self._tile_locks[hash(key) % len(self._tile_locks)]:
            with self._lock:
                entry = self._cache.get(key)
            now = time.monotonic()
            if entry is not None and (entry.source == source if source is not None
                                      else now - entry.fetched < max_age):
                return entry
            client = self.client()
            if client is None:
                return None
            try:
                data, reply_layers = fetch(client, spec)
            except ClientError as exc:
                self.query_failures += 1
                log.debug("tile %s: %s", key, exc)
                return None
            except Exception as exc:  # a session closed under us while reconnecting
                self.query_failures += 1
                log.debug("tile %s: %s: %s", key, type(exc).__name__, exc)
                return None
            self.queries += 1
            digest = hashlib.blake2b(data.tobytes(), digest_size=12,
                                     person=b"sogm-viewer").hexdigest()
            digest += f"-{len(reply_layers)}"
            if entry is not None and entry.digest == digest:
                fresh = CachedTile(digest, entry.png, now, source)  # no new picture
            else:
                fresh = CachedTile(digest, render(spec, data, reply_layers,
                                                  self.settings.filters), now, source)
            with self._lock:
                self._cache[key] = fresh
                self._cache.move_to_end(key)
                while len(self._cache) > self.settings.cache_tiles:
                    self._cache.popitem(last=False)
            return fresh

    def probe(self, x: float, y: float) -> dict[str, Any]:
        """Each layer's probability at the map cell under ``(x, y)``."""
        client = self.client()
        res = self.info.resolution if self.info is not None else None
        if client is None or res is None:
            return {"type": "probe", "x": x, "y": y, "values": [], "error": "not connected"}
        try:
            sub = client.submap(x=x, y=y, width=res, height=res, resolution=res,
                                interp="nearest", encoding="logodds_i16")
        except Exception as exc:  # ClientError, or a session closed while reconnecting
            return {"type": "probe", "x": x, "y": y, "values": [], "error": str(exc)}
        cells = sub.data.reshape(len(sub.layers), -1)[:, 0].astype(np.int64)
        probs = logodds.fixed_to_prob(cells)
        return {"type": "probe", "x": x, "y": y, "values": [
            {"layer": name, "p": round(float(probs[k]), 4), "known": bool(cells[k] != 0)}
            for k, name in enumerate(sub.layers)]}

    def supercells(self, xmin: float, ymin: float, xmax: float, ymax: float,
                   max_side: int = 192) -> dict[str, Any]:
        """The SEVDS graph of a box (at most ``max_side`` cells a side: coarser when larger)."""
        client = self.client()
        info = self.info
        if client is None or info is None:
            return {"type": "supercells", "nodes": [], "edges": [], "error": "not connected"}
        w, h = xmax - xmin, ymax - ymin
        res = max(info.resolution, max(w, h) / max_side)
        patient = MapClient(client.session, client.map_name, client.prefix,
                            self.settings.supercells_timeout_s)  # same session, longer wait
        try:
            reply = patient.supercells(x=(xmin + xmax) / 2, y=(ymin + ymax) / 2, width=w,
                                       height=h, resolution=res)
        except Exception as exc:  # ClientError, or a session closed while reconnecting
            return {"type": "supercells", "nodes": [], "edges": [], "error": str(exc)}
        order = {name: k for k, name in enumerate(info.layers)}
        nodes, edges = [], []
        evidence = node_evidence(np.array([n.mean_probability for n in reply.nodes],
                                          dtype=np.float64).reshape(len(reply.nodes), -1))
        for n, e in zip(reply.nodes, evidence.tolist(), strict=True):
            cls = order.get(reply.layers[e], -1) if e >= 0 else -1
            nodes.append({"id": n.id, "x": round(n.x, 4), "y": round(n.y, 4),
                          "area_m2": round(n.area_m2, 4), "cls": cls, "free": e == FREE})
            edges += [[n.id, m] for m in n.neighbors if n.id < m]
        return {"type": "supercells", "nodes": nodes, "edges": edges,
                "box": [xmin, ymin, xmax, ymax], "resolution": res, "error": None}
