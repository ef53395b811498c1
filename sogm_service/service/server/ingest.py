"""From Zenoh's callback threads to the ingestion worker: a bounded queue and one thread.

Zenoh's callbacks only enqueue the raw payload (after the byte limit), so the network side is
never slowed by decoding or fusion.  The queue is bounded: with the ``lossless`` policy a full
queue blocks the callback, which pushes back through Zenoh to publishers that use congestion
control BLOCK; with ``latest`` only the newest ISM per key waits and the replaced ones are
counted as dropped.  The worker hands each item to the
:class:`~sogm_service.service.server.pipeline.IngestPipeline` in arrival order.

**Push-back and queries.** Zenoh runs subscriber and queryable callbacks on the threads of its
receive runtime (two by default): a callback blocked on the full queue holds its thread, and
the link it reads stops (that is the push-back).  Two publishers flooding a server held both
threads, and a query waited until the ingestion queue had room: sub-maps took 63 ms median,
422 ms p99, against 16 ms idle.  So the server gives the receive runtime more threads than the
links that may push back at once (:func:`reserve_rx_threads`, ``[limits] rx_threads``), and
counts how many callbacks wait at once (``rx_waiting_max`` in ``stats``).
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from sogm_service.service.server.pipeline import IsmItem
from sogm_service.service.server.stats import Stats

log = logging.getLogger(__name__)

RUNTIME_ENV = "ZENOH_RUNTIME"


@contextmanager
def reserve_rx_threads(threads: int) -> Iterator[bool]:
    """Open the process's first Zenoh session within this block to give Zenoh's receive
    runtime ``threads`` workers (its ``ZENOH_RUNTIME`` environment, read once, when the
    runtime starts); an explicit environment setting wins.  Yields True when set here; the
    environment is left as it was afterwards, so child processes do not inherit it."""
    if RUNTIME_ENV in os.environ:
        log.info("Zenoh runtime from the environment: %s=%s", RUNTIME_ENV,
                 os.environ[RUNTIME_ENV][:200])
        yield False
        return
    os.environ[RUNTIME_ENV] = f"(rx: (worker_threads: {int(threads)}))"
    try:
        yield True
    finally:
        os.environ.pop(RUNTIME_ENV, None)


class IngestQueue:
    """Bounded hand-off from Zenoh callbacks to the worker, ``lossless`` or ``latest``.

    A ``lossless`` queue that is full holds its callbacks back (the push-back) until the
    worker has taken half of it, not just one ISM: when a busy server's queue is always full,
    waking a callback per ISM taken costs a thread switch, and a handover of the interpreter
    lock, for every ISM (a fifth of a capped member's ingestion time); waking them once per
    half queue lets each put a run of ISMs in one go."""

    def __init__(self, size: int, policy: str, stats: Stats) -> None:
        self.policy = policy
        self._size = size
        self._refill = size // 2  # waiting callbacks are woken at this depth
        self._stats = stats
        self._fifo: collections.deque[IsmItem] = collections.deque()
        self._latest: dict[str, IsmItem] = {}
        lock = threading.Lock()
        self._cond = threading.Condition(lock)  # the worker waits on it for items
        self._room = threading.Condition(lock)  # callbacks wait on it for room
        self._closed = False
        self._waiting = 0
        self.waiting_max = 0
        """The most callbacks that waited on the full queue at once (each holds a Zenoh
        receive thread)."""

    def put(self, item: IsmItem) -> bool:
        """Enqueue; ``lossless`` blocks while full.  False once the queue is closed."""
        if self._closed:
            return False
        with self._cond:
            if self.policy == "lossless":
                if len(self._fifo) >= self._size and not self._wait_room():
                    return False
                self._fifo.append(item)
            else:
                if item.key in self._latest:
                    self._stats.count("isms_dropped_latest")
                self._latest[item.key] = item
            self._cond.notify()
        return True

    def _wait_room(self) -> bool:
        """The push-back (the lock held): wait for room, counting the callbacks waiting at
        once.  False when the queue closes meanwhile."""
        self._waiting += 1
        self.waiting_max = max(self.waiting_max, self._waiting)
        self._stats.count("isms_pushed_back")
        try:
            while len(self._fifo) > self._refill:  # then, not at the first free place
                if self._closed:
                    return False
                self._room.wait(0.2)
            return True
        finally:
            self._waiting -= 1

    def get(self, timeout: float) -> IsmItem | None:
        with self._cond:
            items = self._fifo if self.policy == "lossless" else self._latest
            if not items and not self._cond.wait_for(lambda: bool(items), timeout):
                return None
            if self.policy != "lossless":
                key = next(iter(self._latest))
                return self._latest.pop(key)
            item = self._fifo.popleft()
            if self._waiting and len(self._fifo) <= self._refill:
                self._room.notify_all()
            return item

    def depth(self) -> int:
        return len(self._fifo) if self.policy == "lossless" else len(self._latest)

    def close(self) -> None:
        """Refuse new items; what is queued stays for the worker to finish."""
        self._closed = True


class IngestWorker:
    """The thread that drains an :class:`IngestQueue` into ``handle``, in arrival order."""

    def __init__(self, items: IngestQueue, handle: Callable[[IsmItem], None],
                 stats: Stats) -> None:
        self.items = items
        self._handle = handle
        self._stats = stats
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sogm-ingest", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float) -> None:
        """Finish what is queued (the queue must be closed first), then end the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            item = self.items.get(timeout=0.1)
            if item is None:
                if self._stop.is_set() and self.items.depth() == 0:
                    return
                continue
            self._handle(item)

    def wait_idle(self, timeout: float) -> bool:
        """Block until the queue is empty and every received ISM has been handled."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            counters, _ = self._stats.snapshot()
            done = (counters.get("isms_fused", 0) + counters.get("isms_rejected", 0)
                    + counters.get("isms_dropped_latest", 0))
            if self.items.depth() == 0 and done >= counters.get("isms_received", 0):
                return True
            time.sleep(0.01)
        return False
