"""The web side of the viewer: a Starlette app with the page and one WebSocket per browser.

Per browser (one :class:`Connection`) four asyncio tasks run:

* *sender*: takes messages from the connection's :class:`~.outbox.Outbox` (bounded,
  drop-oldest) and writes them to the socket.  A slow browser only ever fills its own outbox.
* *receiver*: reads the page's requests (``view``, ``probe``, ``supercells``), validates them and
  records the latest of each (a page sending faster than it is answered only replaces its
  request).
* *refresher*: every ``refresh_s`` seconds, or at once after a new view, an ``info`` change or a
  tile event, works out the visible known display tiles (:mod:`.tiles`), checks the versions of
  the map tiles under them with one ``tiles/changed`` query (:mod:`.versions`, shared by every
  page), gets from the hub's shared cache the display tiles (asked of the map server again only
  when the versions under them moved) and sends only those whose cells changed since this
  browser got them.  It skips a round while the outbox still holds tiles the browser has not
  taken, so a stuck page causes no queries.
* *answers*: answers the latest ``probe`` and ``supercells`` request.

Queries to the map server run on one small thread pool shared by all browsers: however many
pages are open, the viewer asks at most ``workers`` queries at a time.

Security: the page and socket answer only requests whose ``Host`` header names this server
(DNS rebinding), and the socket refuses a browser ``Origin`` other than the page's own
(cross-site WebSocket hijacking).  There is no login: never listen beyond loopback without the
secure set-up in front (README: SSH tunnel or a TLS reverse proxy with authentication).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import struct
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from sogm_service.apps.viewer.hub import MapHub, Updates
from sogm_service.apps.viewer.outbox import Message, Outbox
from sogm_service.apps.viewer.tiles import (
    TileSpec,
    View,
    ViewError,
    known_at_level,
    parse_view,
    visible_tiles,
)
from sogm_service.apps.viewer.versions import lattice_bounds, source_of

log = logging.getLogger("sogm_service.apps.viewer")

MAX_REQUEST_BYTES = 16 * 1024
"""Largest message a page may send (a view is ~300 bytes)."""
TICK_S = 0.1
"""How often poses, events and stats are pushed (10 Hz at most, whatever the fleet sends)."""

_STATIC = {"viewer.js": "text/javascript; charset=utf-8",
           "viewer.css": "text/css; charset=utf-8",
           "index.html": "text/html; charset=utf-8"}
_HEADERS = {
    # Everything comes from this server; no inline script, no CDN: the page works offline.
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data: blob:; "
                               "connect-src 'self'; style-src 'self'; script-src 'self'; "
                               "object-src 'none'; base-uri 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def _static(name: str) -> bytes:
    return resources.files("sogm_service.apps.viewer").joinpath("static", name).read_bytes()


def _json(obj: dict[str, Any]) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


class Connection:
    """One browser."""

    def __init__(self, ws: WebSocket, hub: MapHub, pool: ThreadPoolExecutor,
                 refresh_s: float, outbox_size: int, workers: int = 2) -> None:
        self.ws = ws
        self.hub = hub
        self.pool = pool
        self.workers = max(1, workers)
        self.refresh_s = refresh_s
        self.outbox = Outbox(outbox_size)
        self.view: View | None = None
        self.sent: dict[str, str] = {}
        self.pending: dict[str, str] = {}
        self.wake = asyncio.Event()
        self.asked = asyncio.Event()
        self.probe_request: tuple[float, float] | None = None
        self.supercell_request: tuple[float, float, float, float] | None = None
        self.refreshes = 0
        self.tiles_sent = 0

    # -- plumbing -------------------------------------------------------------------------
    def send(self, obj: dict[str, Any], droppable: bool = True) -> None:
        try:
            text = _json(obj)
        except (TypeError, ValueError):  # NaN or an unexpected type: never kill the loop
            log.warning("viewer: dropped an unencodable %s message", obj.get("type"))
            return
        self.outbox.put(Message(text, droppable=droppable, kind=str(obj.get("type"))))

    def push(self, updates: Updates) -> None:
        """Hub updates for this browser (called by the app's ticker)."""
        if updates.status is not None:
            self.send(updates.status, droppable=False)
        if updates.info is not None:
            self.send(updates.info, droppable=False)
            self.wake.set()
        if updates.poses:
            self.send({"type": "poses", "poses": updates.poses})
        if updates.events:
            self.send({"type": "tile_events", "events": updates.events}, droppable=False)
            self.wake.set()
        if updates.footprints:
            self.send({"type": "footprints", "footprints": updates.footprints})
        if updates.stats is not None:
            self.send(updates.stats)

    async def run(self) -> None:
        await self.ws.accept()
        self.send(self.hub.hello(), droppable=False)
        tasks = [asyncio.create_task(c) for c in
                 (self._sender(), self._receiver(), self._refresher(), self._answers())]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            self.outbox.close()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _sender(self) -> None:
        while True:
            msg = await self.outbox.get()
            if msg is None:
                return
            if isinstance(msg.data, bytes):
                await self.ws.send_bytes(msg.data)
            else:
                await self.ws.send_text(msg.data)
            if msg.on_sent is not None:
                msg.on_sent()

    async def _receiver(self) -> None:
        with contextlib.suppress(WebSocketDisconnect):
            while True:
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    return
                text = message.get("text")
                if text is None:
                    self.send({"type": "error", "code": "bad_json",
                               "message": "requests are JSON text"}, droppable=False)
                    continue
                self.handle(text)

    def handle(self, text: str) -> None:
        """One request from the page; a bad one gets an ``error`` reply and changes nothing."""
        try:
            if len(text) > MAX_REQUEST_BYTES:
                raise ViewError("too_large", f"requests are limited to {MAX_REQUEST_BYTES} bytes")
            try:
                msg = json.loads(text)
            except ValueError:
                raise ViewError("bad_json", "a request must be a JSON object") from None
            if not isinstance(msg, dict):
                raise ViewError("bad_json", "a request must be a JSON object")
            kind = msg.get("type")
            if kind == "view":
                view = parse_view(msg, self.hub.layers())
                self.view = view
                self.send({"type": "view_ack", "signature": view.signature(),
                           "seq": msg.get("seq") if isinstance(msg.get("seq"), int) else None},
                          droppable=False)
                self.wake.set()
            elif kind == "probe":
                x, y = _finite(msg, "x"), _finite(msg, "y")
                self.probe_request = (x, y)
                self.asked.set()
            elif kind == "supercells":
                box = tuple(_finite(msg, k) for k in ("xmin", "ymin", "xmax", "ymax"))
                if not (box[0] < box[2] and box[1] < box[3]):
                    raise ViewError("bad_box", "the supercell box is empty")
                self.supercell_request = box  # type: ignore[assignment]
                self.asked.set()
            else:
                raise ViewError("unknown_request", f"unknown request type {kind!r}")
        except ViewError as exc:
            self.send({"type": "error", "code": exc.code, "message": str(exc)}, droppable=False)

    async def _answers(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self.asked.wait()
            self.asked.clear()
            probe, self.probe_request = self.probe_request, None
            if probe is not None:
                self.send(await loop.run_in_executor(self.pool, self.hub.probe, *probe),
                          droppable=False)
            box, self.supercell_request = self.supercell_request, None
            if box is not None:
                self.send(await loop.run_in_executor(self.pool, self.hub.supercells, *box),
                          droppable=False)

    # -- tiles ----------------------------------------------------------------------------
    async def _refresher(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.wake.wait(), self.refresh_s)
            self.wake.clear()
            try:
                await self.refresh()
            except Exception:  # a bug must not close the page's connection
                log.exception("viewer: refresh failed")

    async def refresh(self) -> None:
        view, lattice = self.view, self.hub.lattice()
        if view is None or lattice is None or not self.hub.connected:
            return
        if self.outbox.count("tile") > self.outbox.capacity // 4:
            return  # the browser has not taken the last round yet: ask the server nothing
        level = lattice.level_for(view.px_per_m)
        specs = visible_tiles(view, lattice, known_at_level(self.hub.known_tiles(), level),
                              level)
        needed = {s.key for s in specs}
        gone = [k for k in {*self.sent, *self.pending} if k not in needed]
        for k in gone:
            self.sent.pop(k, None)
            self.pending.pop(k, None)
        if gone:
            self.send({"type": "drop", "keys": gone}, droppable=False)
        loop = asyncio.get_running_loop()
        bounds = lattice_bounds(specs)
        versions = None if bounds is None else await loop.run_in_executor(
            self.pool, self.hub.versions, bounds, self.refresh_s)
        sent = 0
        for first in range(0, len(specs), self.workers):  # as many at once as the pool runs
            if self.view is not view:
                break  # the page moved on: start over with the new view
            chunk = specs[first:first + self.workers]
            sources = [None if versions is None else source_of(s, versions) for s in chunk]
            got = await asyncio.gather(*(
                loop.run_in_executor(self.pool, self.hub.tile, spec, self.refresh_s, src)
                for spec, src in zip(chunk, sources, strict=True)))
            for spec, tile in zip(chunk, got, strict=True):
                if tile is None:
                    continue
                key = spec.key
                if self.sent.get(key) == tile.digest or self.pending.get(key) == tile.digest:
                    continue
                self._queue_tile(spec, tile.digest, tile.png)
                sent += 1
            if any(t is None for t in got):
                break  # the server is away or refusing: try again next round
        self.refreshes += 1
        self.send({"type": "refreshed", "n": self.refreshes, "sent": sent,
                   "tiles": len(specs), "level": level, "signature": view.signature(),
                   "checked": versions is not None})

    def _queue_tile(self, spec: TileSpec, digest: str, png: bytes) -> None:
        key = spec.key
        header = _json({"type": "tile", "key": key, "signature": spec.signature,
                        "level": spec.level, "a": spec.a, "b": spec.b, "x0": spec.x0,
                        "y0": spec.y0, "span": spec.span, "pixels": spec.pixels})
        head = header.encode()
        self.pending[key] = digest

        def sent() -> None:
            if self.pending.get(key) == digest:
                del self.pending[key]
                self.sent[key] = digest
                self.tiles_sent += 1

        def dropped() -> None:
            if self.pending.get(key) == digest:
                del self.pending[key]

        self.outbox.put(Message(struct.pack(">I", len(head)) + head + png, kind="tile",
                                on_sent=sent, on_drop=dropped))


def _finite(msg: dict[str, Any], name: str) -> float:
    v = msg.get(name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
            or abs(v) > 1e7:
        raise ViewError("bad_number", f"{name} must be a finite number of metres")
    return float(v)


def create_app(hub: MapHub, *, refresh_s: float = 1.0, allowed_hosts: list[str] | None = None,
               workers: int = 2, outbox_size: int = 256, start_hub: bool = True) -> Starlette:
    """The viewer's ASGI app over ``hub`` (started and closed with the app's lifespan)."""
    connections: set[Connection] = set()
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="viewer-query")
    pages = {name: _static(name) for name in _STATIC}

    async def ticker() -> None:
        while True:
            await asyncio.sleep(TICK_S)
            updates = hub.drain()
            if updates:
                for conn in list(connections):
                    try:
                        conn.push(updates)
                    except Exception:  # one page's trouble is not every page's
                        log.exception("viewer: update of a page failed")

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        if start_hub:
            hub.start()
        task = asyncio.create_task(ticker())
        try:
            yield
        finally:
            task.cancel()
            pool.shutdown(wait=False, cancel_futures=True)
            if start_hub:
                await asyncio.to_thread(hub.close)

    async def index(request: Request) -> Response:
        return Response(pages["index.html"], media_type=_STATIC["index.html"], headers=_HEADERS)

    async def static(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in pages or name == "index.html":
            return Response("not found", status_code=404, media_type="text/plain")
        return Response(pages[name], media_type=_STATIC[name], headers=_HEADERS)

    async def state(request: Request) -> Response:
        """A summary for scripts and health checks."""
        info = hub.info
        return JSONResponse({
            "connected": hub.connected, "error": hub.error, "map": hub.settings.map_name,
            "endpoint": hub.settings.endpoint, "browsers": len(connections),
            "layers": [] if info is None else list(info.layers),
            "tiles": 0 if info is None else len(info.tiles),
            "robots": sorted(hub.robots), "queries": hub.queries,
            "query_failures": hub.query_failures, "checks": hub.book.stats.checks,
            "check_replies": hub.book.stats.replies, "check_bytes": hub.book.stats.bytes,
            "check_fallbacks": hub.book.stats.fallbacks}, headers={"Cache-Control": "no-store"})

    async def socket(ws: WebSocket) -> None:
        origin, host = ws.headers.get("origin"), ws.headers.get("host")
        if origin is not None and urlsplit(origin).netloc != host:
            log.warning("viewer: refused a WebSocket from origin %s (host %s)", origin, host)
            await ws.close(code=1008)
            return
        conn = Connection(ws, hub, pool, refresh_s, outbox_size, workers)
        connections.add(conn)
        try:
            await conn.run()
        finally:
            connections.discard(conn)

    routes = [Route("/", index), Route("/static/{name}", static),
              Route("/api/state", state), WebSocketRoute("/ws", socket)]
    middleware = [Middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts or ["*"])]
    return Starlette(routes=routes, middleware=middleware, lifespan=lifespan)
