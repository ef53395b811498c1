"""ISMs offered while no server can hear them: the latest per key kept, the rest dropped and
counted.

A robot's link drops (WiFi).  Zenoh drops what is put while nothing matches a publisher, and a
backlog of every ISM of an outage would arrive late, all at once, mostly superseded: the map
wants the newest view of each layer, not the history.  So :class:`MapClient
<sogm_service.client.mapclient.MapClient>` keeps, while a key has no route, the latest ISM
per key (``ism/<robot>/<sensor>/<layer>``: one per layer of a sensor) in this bounded buffer,
counts every ISM it replaces or cannot keep, and sends what it kept once the route returns.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import zenoh

DEFAULT_MAX_KEYS = 64
"""Keys (layers of a robot's sensors) the buffer keeps an ISM for; the oldest goes beyond."""

DEFAULT_MAX_BYTES = 32 << 20
"""Bytes of encoded ISMs the buffer keeps at most (32 MiB); the oldest go beyond."""

IN_FLIGHT_S = 15.0
"""How far back a key's puts may have been lost when its route goes: a link that goes silent
is noticed only when Zenoh's lease expires (``transport/link/tx/lease``, 10 s by default),
and what was put meanwhile went into the dead link."""

RECENT_PER_KEY = 512
"""At most this many ids of a key's recent puts are remembered (the oldest go first)."""

ROUTE_WAIT_S = 0.5
"""How long a new ISM key's publisher waits for its first match before the policy holds its
ISM (through a router, a route takes a few milliseconds to be known)."""


@dataclass(frozen=True)
class OfflineStats:
    """What became of the ISMs a client was offered (``MapClient.offline_stats()``).

    ``offered = sent + held + dropped`` at every moment; ``flushed`` counts the sent ones that
    waited in the buffer for the route to return; ``lost_in_flight`` the sent ones that were
    on their way when the link went (known once the server's acknowledgements say so)."""

    offered: int = 0
    sent: int = 0
    held: int = 0
    flushed: int = 0
    dropped_superseded: int = 0  # a newer ISM of the same key replaced it in the buffer
    dropped_overflow: int = 0  # the buffer was full (keys or bytes): the oldest went
    dropped_unsent: int = 0  # still held when the client closed (the route never returned)
    outages: int = 0  # times an ISM found its key without a route after it had one
    lost_in_flight: int = 0  # sent just before a route was lost, and unknown to the server

    @property
    def dropped(self) -> int:
        """Every ISM the policy dropped (superseded, overflow, unsent at close)."""
        return self.dropped_superseded + self.dropped_overflow + self.dropped_unsent


@dataclass(frozen=True)
class HeldIsm:
    """One encoded ISM waiting for a route: its key, payload and id (the Zenoh attachment)."""

    key: str
    payload: bytes
    ism_id: str


class OfflineBuffer:
    """The latest ISM per key while its key has no route; thread-safe.

    :meth:`hold` keeps an ISM and returns the ids of those it dropped; :meth:`take` hands the
    kept ones back, oldest first, to be sent; :meth:`sent` counts what went out."""

    def __init__(self, max_keys: int = DEFAULT_MAX_KEYS,
                 max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_keys < 1 or max_bytes < 1:
            raise ValueError("the offline buffer keeps at least one key and one byte")
        self.max_keys = max_keys
        self.max_bytes = max_bytes
        self._held: OrderedDict[str, HeldIsm] = OrderedDict()
        self._bytes = 0
        self._stats = OfflineStats()
        self._lock = threading.Lock()
        self._routed: set[str] = set()  # keys that had a route (an outage is losing it)
        self._recent: dict[str, deque[tuple[float, str]]] = {}  # key -> (when, id) of puts
        self._suspects: dict[str, None] = {}  # ids put just before their key lost its route

    def __len__(self) -> int:
        with self._lock:
            return len(self._held)

    def stats(self) -> OfflineStats:
        with self._lock:
            return replace(self._stats, held=len(self._held))

    def offered(self) -> None:
        """Count one ISM handed to the client."""
        with self._lock:
            self._stats = replace(self._stats, offered=self._stats.offered + 1)

    def sent(self, key: str, flushed: bool = False, ism_id: str | None = None) -> None:
        """Count one ISM put on the wire (``flushed``: it came out of the buffer)."""
        with self._lock:
            self._routed.add(key)
            if ism_id is not None:
                now = time.monotonic()
                recent = self._recent.setdefault(key, deque(maxlen=RECENT_PER_KEY))
                while recent and recent[0][0] < now - IN_FLIGHT_S:
                    recent.popleft()
                recent.append((now, ism_id))
            self._stats = replace(self._stats, sent=self._stats.sent + 1,
                                  flushed=self._stats.flushed + int(flushed))

    def hold(self, item: HeldIsm) -> list[str]:
        """Keep ``item`` as its key's latest; returns the ids of the ISMs dropped for it."""
        dropped: list[str] = []
        with self._lock:
            stats = self._stats
            if item.key in self._routed:
                self._routed.discard(item.key)
                stats = replace(stats, outages=stats.outages + 1)
                since = time.monotonic() - IN_FLIGHT_S
                self._suspects.update(dict.fromkeys(
                    i for t, i in self._recent.pop(item.key, ()) if t >= since))
            old = self._held.pop(item.key, None)
            if old is not None:
                self._bytes -= len(old.payload)
                dropped.append(old.ism_id)
                stats = replace(stats, dropped_superseded=stats.dropped_superseded + 1)
            overflow = 0
            while self._held and (len(self._held) >= self.max_keys
                                  or self._bytes + len(item.payload) > self.max_bytes):
                _, oldest = self._held.popitem(last=False)
                self._bytes -= len(oldest.payload)
                dropped.append(oldest.ism_id)
                overflow += 1
            if len(item.payload) > self.max_bytes:  # larger than the whole buffer
                dropped.append(item.ism_id)
                overflow += 1
            else:
                self._held[item.key] = item
                self._bytes += len(item.payload)
            self._stats = replace(stats, dropped_overflow=stats.dropped_overflow + overflow)
        return dropped

    def suspects(self) -> list[str]:
        """Ids put shortly before their key lost its route: maybe lost on the way."""
        with self._lock:
            return list(self._suspects)

    def settled(self, ism_id: str, lost: bool) -> None:
        """The server said what became of a suspect (``lost``: it never heard of it)."""
        with self._lock:
            if ism_id in self._suspects:
                del self._suspects[ism_id]
                if lost:
                    self._stats = replace(self._stats,
                                          lost_in_flight=self._stats.lost_in_flight + 1)

    def take(self) -> list[HeldIsm]:
        """Every kept ISM, oldest first, out of the buffer (to send, or :meth:`hold` again)."""
        with self._lock:
            items = list(self._held.values())
            self._held.clear()
            self._bytes = 0
        return items

    def put_back(self, items: list[HeldIsm]) -> list[str]:
        """Return ISMs :meth:`take` gave out that found no route yet (no counting: they are
        the same ISMs), unless a newer one of their key arrived meanwhile; returns the ids of
        those so dropped."""
        dropped: list[str] = []
        with self._lock:
            for item in reversed(items):
                if item.key in self._held:
                    self._stats = replace(
                        self._stats, dropped_superseded=self._stats.dropped_superseded + 1)
                    dropped.append(item.ism_id)
                    continue
                self._held[item.key] = item
                self._held.move_to_end(item.key, last=False)
                self._bytes += len(item.payload)
        return dropped

    def discard(self) -> list[str]:
        """Drop everything still held (the client closes); returns their ids."""
        items = self.take()
        with self._lock:
            self._stats = replace(self._stats,
                                  dropped_unsent=self._stats.dropped_unsent + len(items))
        return [i.ism_id for i in items]


def has_route(pub: zenoh.Publisher) -> bool:
    """Whether a subscriber matching ``pub``'s key is reachable now (Zenoh's matching status:
    it turns false when the link to the router or the server goes, true when Zenoh has
    reconnected and the subscriber is declared again)."""
    status = pub.matching_status  # a MatchingStatus at run time, whatever the stub says
    return bool(getattr(status, "matching", status))


class OfflinePolicy:
    """Puts an ISM when its key has a route, else holds it as its key's latest.

    ``publisher(key)`` gives the client's publisher of a key; ``forget(ids)`` is told the ids
    of the ISMs the policy dropped.  Held ISMs go out, oldest first, before the next ISM that
    finds a route, or on :meth:`flush`."""

    def __init__(self, publisher: Callable[[str], zenoh.Publisher],
                 forget: Callable[[list[str]], None],
                 buffer: OfflineBuffer | None = None) -> None:
        self.buffer = buffer or OfflineBuffer()
        self._publisher = publisher
        self._forget = forget
        self._waited: set[str] = set()

    def send(self, item: HeldIsm) -> None:
        self.buffer.offered()
        pub = self._publisher(item.key)
        if item.key not in self._waited:  # a new key: its first match takes a moment
            self._waited.add(item.key)
            deadline = time.monotonic() + ROUTE_WAIT_S
            while not has_route(pub) and time.monotonic() < deadline:
                time.sleep(0.002)
        if has_route(pub):
            self.flush()
            pub.put(item.payload, attachment=item.ism_id.encode("ascii"))
            self.buffer.sent(item.key, ism_id=item.ism_id)
        else:
            self._forget(self.buffer.hold(item))

    def flush(self, timeout: float = 0.0) -> int:
        """Send the held ISMs whose key has a route, waiting up to ``timeout`` seconds for the
        rest; returns how many are still held."""
        deadline = time.monotonic() + timeout
        while True:
            waiting = []
            for item in self.buffer.take():
                pub = self._publisher(item.key)
                if has_route(pub):
                    pub.put(item.payload, attachment=item.ism_id.encode("ascii"))
                    self.buffer.sent(item.key, flushed=True, ism_id=item.ism_id)
                else:
                    waiting.append(item)
            self._forget(self.buffer.put_back(waiting))
            if not waiting or time.monotonic() >= deadline:
                return len(self.buffer)
            time.sleep(0.05)

    def settle(self, status: Callable[[str], str]) -> int:
        """Ask ``status(id)`` (the server's acknowledgement) about each ISM put just before its
        key lost its route; returns how many the server never heard of (lost in flight).
        Those it cannot be asked about yet stay suspects."""
        lost = 0
        for ism_id in self.buffer.suspects():
            try:
                state = status(ism_id)
            except Exception:  # no answer (yet): the rest stay suspects for the next settle
                break
            self.buffer.settled(ism_id, state == "unknown")
            lost += state == "unknown"
        return lost
