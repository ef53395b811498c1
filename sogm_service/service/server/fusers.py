"""Fusing ISMs on several threads over disjoint tiles (architecture, section 7:
docs/architecture.md#7-queries-never-wait-behind-ingestion).

Tile ``(i, j)`` belongs to fuse worker ``j mod K``: a whole row of tiles to one worker, since
a rotated ISM is warped a row of tiles at a time (a band spanning the footprint,
:func:`sogm_service.core.resample.tile_patches`) and a worker sharing a row with another would
warp that band again; neighbouring rows (an ISM usually spans two or three) go to different
workers.  The ingestion worker hands every prepared ISM to the workers that own one of its
tiles, in arrival order; each worker warps the bands of its rows (the bits do not depend on
the split) and adds only its own tiles (:meth:`sogm_service.core.map.tiles.TiledMap.fuse` with
``owned``), in the order it got them.  So every tile sees the ISMs that touch it in arrival
order, whatever K: the map is bit-identical to one worker's.  The resampling (OpenCV warps)
and the add release the GIL, so the workers run on several cores at once; queues between them
are short and bounded, so a full worker pushes back to the ingestion queue (and from there to
the publishers).

With ``K = 1`` the ingestion worker fuses itself (no hand-off at all).
"""

from __future__ import annotations

import logging
import queue
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.core.resample import Interp

log = logging.getLogger(__name__)

Done = Callable[[list[TileIndex], BaseException | None], None]

_QUEUE_SIZE = 4  # ISMs waiting per worker: enough to keep it busy, little memory



def ism_digest(payload: bytes) -> int:
    """A cheap 64-bit identity of an ISM's payload (CRC-32 and Adler-32 side by side)."""
    return (zlib.crc32(payload) << 32) | zlib.adler32(payload)

@dataclass
class FuseJob:
    """One ISM to fuse; ``done(touched, error)`` runs once, when every share is fused."""

    layer: str
    increments: npt.NDArray[np.int16]
    geometry: GridGeometry
    interp: Interp
    stamp: float
    done: Done
    key: str = ""  # the ISM key and identity (a cluster member's handover needs them)
    digest: int = 0
    allowed: frozenset[TileIndex] | None = None  # the tiles this member may write (cluster)
    _parts: int = field(default=0, init=False)
    _touched: list[TileIndex] = field(default_factory=list, init=False)
    _error: BaseException | None = field(default=None, init=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False)

    def fuse(self, tiled: TiledMap, owned: Callable[[TileIndex], bool] | None) -> None:
        """Fuse this worker's share; the last share to finish reports the whole ISM."""
        touched: list[TileIndex] = []
        error: BaseException | None = None
        allowed = self.allowed
        if allowed is not None:
            share = owned

            def owned(index: TileIndex) -> bool:
                return index in allowed and (share is None or share(index))
        try:
            touched = tiled.fuse(self.layer, self.increments, self.geometry, self.interp,
                                 self.stamp, owned,
                                 (self.key, (self.stamp, self.digest)) if self.key else None)
        except Exception as exc:  # reported with the ISM; never ends the worker
            error = exc
        with self._lock:
            self._touched.extend(touched)
            self._error = self._error or error
            self._parts -= 1
            last = self._parts == 0
        if last:
            self.done(sorted(self._touched), self._error)


class FuseWorkers:
    """``workers`` fuse threads, each owning the rows of tiles ``j mod workers`` of its number."""

    def __init__(self, tiled: TiledMap, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"need at least one fuse worker, got {workers}")
        self.tiled = tiled
        self.workers = workers
        self._queues: list[queue.Queue[FuseJob | None]] = []
        self._threads: list[threading.Thread] = []
        self._idle = threading.Condition()
        self._pending = 0
        self.scope: Callable[[FuseJob], frozenset[TileIndex] | None] | None = None
        """A cluster member's share of the map: the tiles of a job it may write."""
        if workers > 1:
            for k in range(workers):
                q: queue.Queue[FuseJob | None] = queue.Queue(maxsize=_QUEUE_SIZE)
                t = threading.Thread(target=self._run, args=(k, q), name=f"sogm-fuse-{k}",
                                     daemon=True)
                self._queues.append(q)
                self._threads.append(t)
                t.start()

    def owner(self, index: TileIndex) -> int:
        return index[1] % self.workers

    def submit(self, job: FuseJob) -> None:
        """Fuse ``job`` (at once with one worker; else queued to the workers owning its tiles,
        blocking while their queues are full)."""
        if self.scope is not None:
            job.allowed = self.scope(job)
        if self.workers == 1:
            job._parts = 1
            job.fuse(self.tiled, None)
            return
        owners = sorted({self.owner(i) for i in self.tiled.lattice.tiles_overlapping(
            job.geometry) if job.allowed is None or i in job.allowed})
        if not owners:
            job._parts = 1
            job.fuse(self.tiled, lambda index: False)
            return
        job._parts = len(owners)
        with self._idle:
            self._pending += len(owners)
        for k in owners:
            self._queues[k].put(job)

    def _run(self, k: int, jobs: queue.Queue[FuseJob | None]) -> None:
        def mine(index: TileIndex) -> bool:
            return self.owner(index) == k

        while True:
            job = jobs.get()
            if job is None:
                return
            try:
                job.fuse(self.tiled, mine)
            except Exception:  # a failing ``done`` must not end the worker
                log.exception("fuse worker %d: reporting an ISM failed", k)
            with self._idle:
                self._pending -= 1
                if self._pending == 0:
                    self._idle.notify_all()

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every submitted ISM is fused (scan matching reads the map first)."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout)

    def close(self, timeout: float) -> None:
        """Finish what is queued, then end the threads."""
        for q in self._queues:
            q.put(None)
        for t in self._threads:
            t.join(timeout)
