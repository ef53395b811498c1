"""The background tile writer: snapshots go to disk on their own thread (the paper's double
buffer), so ingestion never waits for it."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sogm_service.core.map.tiletypes import LoaderResult, Mark, TileIndex
from sogm_service.store.protocol import TileStore
from sogm_service.wire.tilefile import Fixed, check_stack

log = logging.getLogger(__name__)


@dataclass
class _Job:
    index: TileIndex
    layers: tuple[str, ...]
    data: Fixed
    stamp: float
    token: Any
    decay: dict[str, float] | None = None
    applied: dict[str, Mark] | None = None


@dataclass
class WriterStats:
    written: int = 0
    coalesced: int = 0
    errors: int = 0
    bytes_written: int = 0
    seconds: float = 0.0
    last_error: str | None = None


SavedCallback = Callable[[TileIndex, Any], None]
ErrorCallback = Callable[[TileIndex, Any, BaseException], None]


class TileWriter:
    """Writes tile snapshots on a background thread so that ingestion never waits for disk.

    :meth:`submit` takes a snapshot the caller already *copied* (the double buffer) and returns
    at once.  A tile submitted again before its write started is coalesced: only the newest
    snapshot is written.  ``on_saved(index, token)`` runs on the writer thread once that
    snapshot is on disk (the server marks the tile clean with ``token``, e.g. its version);
    ``on_error(index, token, exc)`` on a failed write: the tile stays dirty on the caller's side,
    so its next checkpoint retries it.
    """

    def __init__(self, store: TileStore, on_saved: SavedCallback | None = None,
                 on_error: ErrorCallback | None = None) -> None:
        self.store = store
        self.on_saved = on_saved
        self.on_error = on_error
        self.stats = WriterStats()
        self._cond = threading.Condition()
        self._pending: dict[TileIndex, _Job] = {}
        self._busy: _Job | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="sogm-tile-writer", daemon=True)
        self._thread.start()

    def submit(self, i: int, j: int, layers: list[str] | tuple[str, ...], data: Fixed,
               stamp: float, token: Any = None,
               decay: dict[str, float] | None = None,
               applied: dict[str, Mark] | None = None) -> None:
        """Queue a snapshot of tile ``(i, j)``; ``data`` must be a private copy (it is made
        read-only here, so an accidental live array fails loudly instead of tearing).
        ``applied``: the tile's marks (``Tile.applied``), stored with it."""
        check_stack(tuple(layers), data, self.store.expect.tile_size)
        data.setflags(write=False)
        job = _Job((i, j), tuple(layers), data, float(stamp), token, dict(decay or {}),
                   dict(applied or {}))
        with self._cond:
            if self._closing:
                raise RuntimeError("tile writer is closed")
            if job.index in self._pending:
                self.stats.coalesced += 1
            self._pending[job.index] = job
            self._cond.notify_all()

    def pending(self) -> int:
        """Snapshots queued or being written."""
        with self._cond:
            return len(self._pending) + (self._busy is not None)

    def pending_bytes(self) -> int:
        """Bytes of the snapshots queued or being written (what the queue holds in memory)."""
        with self._cond:
            held = sum(job.data.nbytes for job in self._pending.values())
            return held + (self._busy.data.nbytes if self._busy is not None else 0)

    def is_pending(self, i: int, j: int) -> bool:
        with self._cond:
            return (i, j) in self._pending or (self._busy is not None
                                               and self._busy.index == (i, j))

    def loader(self, i: int, j: int) -> LoaderResult | None:
        """Like :meth:`TileStore.loader`, but a snapshot still waiting for disk wins, so a tile
        evicted right after its submit comes back with its newest content (a writable copy)."""
        with self._cond:
            job = self._pending.get((i, j))
            if job is None and self._busy is not None and self._busy.index == (i, j):
                job = self._busy
        if job is not None:
            if isinstance(job.token, int) and job.token > 0:  # the tile's version
                return (list(job.layers), job.data.copy(), job.stamp, dict(job.decay or {}),
                        dict(job.applied or {}), job.token)
            if job.applied:
                return (list(job.layers), job.data.copy(), job.stamp, dict(job.decay or {}),
                        dict(job.applied))
            if job.decay:
                return list(job.layers), job.data.copy(), job.stamp, dict(job.decay)
            return list(job.layers), job.data.copy(), job.stamp
        return self.store.loader(i, j)

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every snapshot submitted so far is on disk (or failed); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._pending and self._busy is None,
                                       timeout)

    def close(self, timeout: float | None = None) -> bool:
        """Write what is queued, then stop the thread; False if that did not finish in time."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._closing)
                if not self._pending:
                    return  # closing and drained
                job = self._pending.pop(next(iter(self._pending)))
                self._busy = job
            try:
                self._write(job)
            finally:
                with self._cond:
                    self._busy = None
                    self._cond.notify_all()

    def _write(self, job: _Job) -> None:
        t0 = time.perf_counter()
        try:
            info = self.store.write(job.index[0], job.index[1], job.layers, job.data, job.stamp,
                                    job.decay or None, job.applied or None,
                                    job.token if isinstance(job.token, int) else 0)
        except Exception as exc:  # disk full, permissions: report, never kill the thread
            self.stats.errors += 1
            self.stats.last_error = f"tile {job.index}: {exc}"
            log.error("writing tile %s failed: %s", job.index, exc)
            self._callback(self.on_error, job.index, job.token, exc)
            return
        self.stats.written += 1
        self.stats.bytes_written += info.size
        self.stats.seconds += time.perf_counter() - t0
        self._callback(self.on_saved, job.index, job.token)

    @staticmethod
    def _callback(fn: Callable[..., None] | None, *args: Any) -> None:
        if fn is None:
            return
        try:
            fn(*args)
        except Exception:  # a buggy callback must not stop persistence
            log.exception("tile writer callback failed")

