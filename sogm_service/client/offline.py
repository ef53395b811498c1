"""ISMs offered while no server can hear them: the latest per key kept, the rest dropped and
counted; ISMs lost on a link as it went sent again under the same rule.

A robot's link drops (WiFi).  Zenoh drops what is put while nothing matches a publisher, and a
backlog of every ISM of an outage would arrive late, all at once, mostly superseded: the map
wants the newest view of each layer, not the history.  So :class:`MapClient
<sogm_service.client.mapclient.MapClient>` keeps, while a key has no route, the latest ISM
per key (``ism/<robot>/<sensor>/<layer>``: one per layer of a sensor) in this bounded buffer,
counts every ISM it replaces or cannot keep, and sends what it kept once the route returns.

A link that goes silent is noticed only when Zenoh's lease expires; what was put meanwhile
went into the dead link.  The buffer also keeps a copy of the last ISM put on each key (in the
same bounds: one ISM per key, held or copied), remembers the ids put lately, and when the
server's acknowledgements say some of them never arrived, treats them like ISMs offered
during the outage: the newest of a key is held again and sent (unless a newer one of the key
is held or was sent), the older ones are dropped as superseded.
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

ASK_S = 2.0
"""Budget of one acknowledgement asked by :meth:`OfflinePolicy.settle`: a query put into a
silent link gets no answer, and is asked again (within the settle's budget) once Zenoh has
noticed and reconnected."""


GRACE_S = 0.5
"""A last put the server does not know yet is asked about once more after this long (on a
live link it may still be on its way), so nothing that arrives is sent twice."""


@dataclass(frozen=True)
class OfflineStats:
    """What became of the ISMs a client was offered (``MapClient.offline_stats()``).

    ``offered = sent + held + dropped`` at every moment.  ``sent`` counts an ISM once however
    often it went out; one the server never received leaves it when it is held again (to be
    sent once more) or dropped as superseded.  ``flushed`` counts the sent ones that waited in
    the buffer, ``resent`` those of them that had been lost on the way once; ``lost_in_flight``
    the sent ones unknown to the server that the client could not send again (their copy was
    gone: see :meth:`OfflineBuffer.settled`)."""

    offered: int = 0
    sent: int = 0
    held: int = 0
    flushed: int = 0
    resent: int = 0  # flushed after the server's acks said it had never arrived
    dropped_superseded: int = 0  # a newer ISM of the same key replaced it (held or sent)
    dropped_overflow: int = 0  # the buffer was full (keys or bytes): the oldest went
    dropped_unsent: int = 0  # still held when the client closed (the route never returned)
    outages: int = 0  # times an ISM found its key without a route after it had one
    lost_in_flight: int = 0  # unknown to the server, and no copy left to send again

    @property
    def dropped(self) -> int:
        """Every ISM the policy dropped (superseded, overflow, unsent at close)."""
        return self.dropped_superseded + self.dropped_overflow + self.dropped_unsent


@dataclass(frozen=True)
class HeldIsm:
    """One encoded ISM waiting for a route: its key, payload and id (the Zenoh attachment);
    ``resend``: it was put once and never arrived."""

    key: str
    payload: bytes
    ism_id: str
    resend: bool = False


class OfflineBuffer:
    """The latest ISM per key while its key has no route, and a copy of the last one put on
    each key while it has; thread-safe.

    :meth:`hold` keeps an ISM and returns the ids of those it dropped; :meth:`take` hands the
    kept ones back, oldest first, to be sent; :meth:`sent` counts what went out.  Held ISMs
    and copies share the bounds (``max_keys`` keys, ``max_bytes`` bytes; a key has one or the
    other, never both); copies go first when room is needed."""

    def __init__(self, max_keys: int = DEFAULT_MAX_KEYS,
                 max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_keys < 1 or max_bytes < 1:
            raise ValueError("the offline buffer keeps at least one key and one byte")
        self.max_keys = max_keys
        self.max_bytes = max_bytes
        self._held: OrderedDict[str, HeldIsm] = OrderedDict()
        self._copies: OrderedDict[str, HeldIsm] = OrderedDict()  # key -> its last put
        self._bytes = 0  # of held ISMs and copies
        self._stats = OfflineStats()
        self._lock = threading.Lock()
        self._routed: set[str] = set()  # keys that had a route (an outage is losing it)
        self._recent: dict[str, deque[tuple[float, str]]] = {}  # key -> (when, id) of puts
        self._suspects: dict[str, str] = {}  # id -> key: put lately, maybe lost on the way
        self._unknown: dict[str, list[str]] = {}  # key -> ids the server never received

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

    def sent(self, item: HeldIsm, flushed: bool = False) -> None:
        """Count one ISM put on the wire (``flushed``: it came out of the buffer) and keep a
        copy of it as its key's last put (when it fits beside what is held)."""
        with self._lock:
            self._routed.add(item.key)
            now = time.monotonic()
            recent = self._recent.setdefault(item.key, deque(maxlen=RECENT_PER_KEY))
            while recent and recent[0][0] < now - IN_FLIGHT_S:
                recent.popleft()
            recent.append((now, item.ism_id))
            self._drop_copy(item.key)
            self._make_room(len(item.payload), evict_held=False)
            if self._fits(len(item.payload)):
                self._copies[item.key] = replace(item, resend=False)
                self._bytes += len(item.payload)
            self._stats = replace(self._stats, sent=self._stats.sent + 1,
                                  flushed=self._stats.flushed + int(flushed),
                                  resent=self._stats.resent + int(flushed and item.resend))

    def routed_keys(self) -> list[str]:
        """Keys that had a route when they last put an ISM."""
        with self._lock:
            return list(self._routed)

    def lost_route(self, key: str) -> bool:
        """``key`` has no route now: an outage if it had one (counted; its puts of the last
        :data:`IN_FLIGHT_S` become suspects).  Returns whether this was news."""
        with self._lock:
            return self._lose(key)

    def hold(self, item: HeldIsm) -> list[str]:
        """Keep ``item`` as its key's latest; returns the ids of the ISMs dropped for it."""
        dropped: list[str] = []
        with self._lock:
            self._lose(item.key)
            self._drop_copy(item.key)  # the held one is newer than any put before it
            stats = self._stats
            old = self._held.pop(item.key, None)
            if old is not None:
                self._bytes -= len(old.payload)
                dropped.append(old.ism_id)
                stats = replace(stats, dropped_superseded=stats.dropped_superseded + 1)
            overflow = self._make_room(len(item.payload), evict_held=True)
            dropped += overflow
            if len(item.payload) > self.max_bytes:  # larger than the whole buffer
                dropped.append(item.ism_id)
                overflow.append(item.ism_id)
            else:
                self._held[item.key] = item
                self._bytes += len(item.payload)
            self._stats = replace(stats, dropped_overflow=stats.dropped_overflow + len(overflow))
        return dropped

    def newest(self) -> list[tuple[str, str]]:
        """``(key, id)`` of each key's last put in :data:`IN_FLIGHT_S` whose key has no
        suspects yet: if the server never received it, the key's recent puts are suspects."""
        with self._lock:
            suspected = set(self._suspects.values())
            return [(key, recent[-1][1]) for key, recent in self._recent.items()
                    if recent and key not in suspected]

    def suspect(self, key: str) -> None:
        """The key's puts of the :data:`IN_FLIGHT_S` before its last one become suspects (its
        last one is unknown to the server)."""
        with self._lock:
            self._suspect(key)

    def suspects(self) -> list[str]:
        """Ids put shortly before their key lost its route: maybe lost on the way."""
        with self._lock:
            return list(self._suspects)

    def settled(self, ism_id: str, lost: bool) -> list[str]:
        """The server said what became of a suspect (``lost``: it never heard of it).  Once
        every suspect of its key is answered, the key's lost ones go through the policy: the
        newest is held again to be sent when it is the key's last put (its copy is kept),
        the rest are dropped as superseded; without a copy (evicted, or the lost ones are
        older than what the copy replaced) they count as lost in flight.  Returns the ids
        dropped."""
        with self._lock:
            key = self._suspects.pop(ism_id, None)
            if key is None:
                return []
            if lost:
                self._unknown.setdefault(key, []).append(ism_id)
            if key in self._suspects.values():
                return []
            return self._resolve(key)

    def take(self) -> list[HeldIsm]:
        """Every kept ISM, oldest first, out of the buffer (to send, or :meth:`hold` again)."""
        with self._lock:
            items = list(self._held.values())
            self._held.clear()
            self._bytes -= sum(len(i.payload) for i in items)
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
                self._drop_copy(item.key)
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

    # -- under the lock -------------------------------------------------------------------
    def _lose(self, key: str) -> bool:
        if key not in self._routed:
            return False
        self._routed.discard(key)
        self._stats = replace(self._stats, outages=self._stats.outages + 1)
        self._suspect(key)
        return True

    def _suspect(self, key: str) -> None:
        recent = self._recent.pop(key, None)
        if recent:  # the puts of the lease's span before the last one (or before now)
            since = min(time.monotonic(), recent[-1][0]) - IN_FLIGHT_S
            self._suspects.update({i: key for t, i in recent if t >= since})

    def _drop_copy(self, key: str) -> None:
        copy = self._copies.pop(key, None)
        if copy is not None:
            self._bytes -= len(copy.payload)

    def _fits(self, size: int) -> bool:
        return (len(self._held) + len(self._copies) < self.max_keys
                and self._bytes + size <= self.max_bytes)

    def _make_room(self, size: int, evict_held: bool) -> list[str]:
        """Evict copies, oldest first, then (``evict_held``) held ISMs until ``size`` more
        bytes and one more key fit; returns the ids of the held ones evicted."""
        evicted: list[str] = []
        while not self._fits(size):
            if self._copies:
                self._bytes -= len(self._copies.popitem(last=False)[1].payload)
            elif evict_held and self._held:
                _, oldest = self._held.popitem(last=False)
                self._bytes -= len(oldest.payload)
                evicted.append(oldest.ism_id)
            else:
                break
        return evicted

    def _resolve(self, key: str) -> list[str]:
        unknown = self._unknown.pop(key, [])
        if not unknown:
            return []
        copy = self._copies.get(key)
        stats = self._stats
        if key not in self._held and (copy is None or copy.ism_id not in unknown):
            if copy is None:  # nothing newer went out, and nothing is left to send again
                self._stats = replace(stats, lost_in_flight=stats.lost_in_flight + len(unknown))
                return []
            superseded = unknown  # the copy is newer and was not lost
        elif key in self._held:
            superseded = unknown  # the held one is newer and goes out when the route returns
        else:
            assert copy is not None
            del self._copies[key]
            self._held[key] = replace(copy, resend=True)  # the same bytes, now held again
            superseded = [i for i in unknown if i != copy.ism_id]
            stats = replace(stats, sent=stats.sent - 1)
        self._stats = replace(stats, sent=stats.sent - len(superseded),
                              dropped_superseded=stats.dropped_superseded + len(superseded))
        return superseded


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
            self.buffer.sent(item)
            return
        if self.buffer.lost_route(item.key):  # the link went: the other keys' too, maybe
            for key in self.buffer.routed_keys():
                if not has_route(self._publisher(key)):
                    self.buffer.lost_route(key)
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
                    self.buffer.sent(item, flushed=True)
                else:
                    waiting.append(item)
            self._forget(self.buffer.put_back(waiting))
            if not waiting or time.monotonic() >= deadline:
                return len(self.buffer)
            time.sleep(0.05)

    def settle(self, status: Callable[[str, float], str], timeout: float = 2.0) -> int:
        """Ask ``status(id, budget)`` (the server's acknowledgement) what became of the ISMs
        that may have been lost on the way, within ``timeout`` seconds in all: first each
        key's last put (unknown to the server: the key's recent puts become suspects, which
        covers a link that went silent after the last put), then every suspect.  Lost ones go
        through the policy (:meth:`OfflineBuffer.settled`) and the newest of each key is sent
        again.  Returns how many are lost for good (no copy to send).  Those that get no
        answer within ``timeout`` stay suspects for the next settle."""
        deadline = time.monotonic() + timeout
        lost0 = self.buffer.stats().lost_in_flight

        def ask(ism_id: str) -> str | None:
            while (left := deadline - time.monotonic()) > 0:
                try:
                    return status(ism_id, min(left, ASK_S))
                except Exception:  # no answer yet (a silent link): asked again
                    time.sleep(min(0.1, max(deadline - time.monotonic(), 0.0)))
            return None

        for key, ism_id in self.buffer.newest():
            state = ask(ism_id)
            if state is None:
                break
            if state == "unknown":  # or not arrived yet on a live link: asked once more
                time.sleep(min(GRACE_S, max(deadline - time.monotonic(), 0.0)))
                state = ask(ism_id)
            if state == "unknown":
                self.buffer.suspect(key)
        for ism_id in self.buffer.suspects():
            state = ask(ism_id)
            if state is None:
                break
            self._forget(self.buffer.settled(ism_id, state == "unknown"))
        self.flush(max(deadline - time.monotonic(), 0.0))
        return self.buffer.stats().lost_in_flight - lost0
