"""Writing an ISM into the tiled map (:meth:`Fusing.fuse`, Eq. 1) as a two-phase transaction:
what phase 1 keeps of every tile it will write (:class:`Target`), the per-thread memory of the
warped patches (:class:`Scratch`), and the phases themselves (acquire and pin every tile, roll
back on failure; add each patch under its tile's lock, unpin).

Pure (numpy only, no I/O).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry
from sogm_service.core.map import forget
from sogm_service.core.map.mapstate import MapState
from sogm_service.core.map.tile import Owner, Tile
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.core.resample import Interp, TilePatch, informative, tile_patches


@dataclass(eq=False, slots=True)
class Target:
    """One tile a fuse writes: its patch, the tile (pinned), how phase 1 got it, its version
    then, and the plane to add if the tile lacked the layer."""

    part: TilePatch
    tile: Tile
    how: str  # "resident", "loaded" or "created"
    version: int
    fresh: npt.NDArray[np.int16] | None = None
    pinned: bool = True


SCRATCH_MAX = 64 * 256 * 256 * 4
"""Bytes of warped patches a thread keeps between ISMs, at most (128 int16 tiles of 256)."""


class Scratch(threading.local):
    """Per thread: the memory of one ISM's warped patches (fuse's phase 1 keeps them all until
    phase 2 has added them), kept for the next ISM: fresh arrays of this size are mmapped and
    page-faulted by glibc on every call, which costs as much as the warp.  It grows to the
    largest footprint seen, up to :data:`SCRATCH_MAX`; patches beyond are fresh arrays."""

    def __init__(self) -> None:
        self.buf: npt.NDArray[np.uint8] = np.empty(0, np.uint8)
        self.used = 0

    def reset(self) -> Scratch:
        self.used = 0
        return self

    def take(self, h: int, w: int, dtype: np.dtype) -> npt.NDArray:
        dtype = np.dtype(dtype)
        n = h * w * dtype.itemsize
        start = -(-self.used // 64) * 64
        if start + n > self.buf.size:
            if start + n > SCRATCH_MAX:
                return np.empty((h, w), dtype)
            # A bigger buffer from 0; the patches already taken keep the old one alive.
            self.buf = np.empty(min(SCRATCH_MAX, max(2 * self.buf.size, 4 * n)), np.uint8)
            start = 0
        self.used = start + n
        return self.buf[start:start + n].view(dtype).reshape(h, w)


scratch = Scratch()


class Fusing(MapState):
    """The fuse of a tiled map: :meth:`fuse` and its two phases."""

    def fuse(self, layer: str, inc: npt.NDArray[np.int16], geometry: GridGeometry,
             interp: Interp = "biodds", stamp: float = 0.0,
             owned: Owner | None = None,
             mark: tuple[str, Mark] | None = None) -> list[TileIndex]:
        """Eq. 1: fuse fixed log-odds increments given in ``geometry`` into ``layer``.

        The increments are resampled into every tile the ISM overlaps (``interp``, outside the
        ISM -> 0, i.e. untouched) and added with the clamp; ``owned`` limits this to some tiles
        (a fuse worker's share); ``mark`` (ISM key, (stamp, digest)) is recorded in each tile
        written as the last ISM of that key applied to it.  Returns the tiles written.  Only
        the add holds a lock (the tile's); the ISM's alignment and inverse transform are
        worked out once (:func:`sogm_service.core.resample.tile_patches`).

        Transactional: phase 1 computes every tile's patch, gets or creates (or loads back)
        every tile written, pins them (:meth:`evict` leaves a pinned tile resident) and
        allocates the planes this layer lacks there; phase 2 adds the patches, each under its
        tile's lock.  If phase 1 fails (a patch, the loader, an allocation: ``MemoryError``)
        no tile has changed: the tiles it created or loaded back leave the map again and the
        exception propagates; the layer and the map's clock are not even touched.  Phase 2
        allocates nothing (a decaying layer's work memory is taken in phase 1,
        :class:`~sogm_service.core.map.forget.DecayWork`), and fetches a tile again only if
        :meth:`insert_tile` or :meth:`discard` replaced or removed it meanwhile (a cluster's
        handover).
        """
        # Phase 1: every patch (warped ones into this thread's scratch), a decaying layer's
        # work memory, then every tile.
        parts = list(tile_patches(inc, geometry, self.lattice, interp, owned,
                                  buffers=scratch.reset().take))
        known = self._layer_index.get(layer)
        half_life = self.half_life(known) if known is not None \
            else self._forget.half_life(layer)  # a new layer: its rule, once
        work = forget.decay_work.ensure(self.tile_size) if half_life is not None else None
        targets = self._acquire(parts, known)
        try:  # phase 2: nothing here can fail (see the docstring)
            lid = self.layer_id(layer, create=True)
            self.advance_clock(stamp)
            added = (self._add(target, lid, stamp, mark, work) for target in targets)
            return [index for index in added if index is not None]
        finally:
            self._unpin(targets)

    # -- the two phases of a fuse (fuse's docstring) ---------------------------------------
    def _acquire(self, parts: list[TilePatch], known: int | None) -> list[Target]:
        """Phase 1 after the patches: every tile to write, pinned, with a fresh plane when it
        lacks layer ``known`` (None: a new layer).  On failure: rolled back, re-raised."""
        targets: list[Target] = []
        try:
            for part in parts:
                self._target(part, known, targets)
        except BaseException:
            self._roll_back(targets)
            raise
        return targets

    def _target(self, part: TilePatch, known: int | None, targets: list[Target]) -> None:
        index = part.index
        while True:
            tile, how = self.tiles.get(index), "resident"
            if tile is None:
                useful = informative(part.patch)
                with self._struct:
                    tile = self.tiles.get(index)
                    if tile is None and index in self.stored and self.loader is not None:
                        tile, how = self._load(index), "loaded"
                    if tile is None:
                        if not useful:
                            return  # an ISM of pure unknown creates no tile
                        tile, how = Tile(index, version=self.tick()), "created"
                        self.tiles[index] = tile
            with tile.lock:
                if tile.evicted:
                    continue  # evicted since we found it: fetch it again
                tile.pins += 1
                target = Target(part, tile, how, tile.version)
                lacks = known is None or known not in tile.planes
            targets.append(target)  # pinned: a failure from here on is rolled back
            tile.last_used = time.monotonic()
            if lacks:
                target.fresh = self._new_plane()
            return

    def _roll_back(self, targets: list[Target]) -> None:
        """Phase 1 failed: unpin; the tiles it created or loaded leave the map again unless
        something else has used them for a write since."""
        with self._struct:
            for target in reversed(targets):
                tile = target.tile
                with tile.lock:
                    tile.pins -= 1
                    target.pinned = False
                    if target.how == "resident" or tile.pins or tile.evicted \
                            or tile.version != target.version \
                            or self.tiles.get(tile.index) is not tile:
                        continue
                    tile.evicted = True
                    del self.tiles[tile.index]
                    self._account(-tile.nbytes)
                    if target.how == "loaded":
                        self.stored.add(tile.index)  # as it was: stored, not resident

    def _add(self, target: Target, lid: int, stamp: float, mark: tuple[str, Mark] | None,
             work: forget.DecayWork | None = None) -> TileIndex | None:
        """Phase 2 for one tile: Eq. 1 under its lock, then unpinned."""
        index, (u0, v0, w, h), patch = target.part.index, target.part.block, target.part.patch
        tile: Tile | None = target.tile
        while tile is not None:
            with tile.lock:
                if target.pinned and tile is target.tile:
                    tile.pins -= 1
                    target.pinned = False
                if not tile.evicted:
                    first = lid not in tile.planes
                    plane = self._plane(tile, lid, target.fresh)
                    target.fresh = None
                    half_life = self.half_life(lid)
                    decay_at = tile.decay.get(lid)
                    age = 1.0 if half_life is None else forget.before_write(
                        tile, lid, half_life, stamp, first, work)
                    added = patch if age == 1.0 else forget.aged(patch, age, work)
                    logodds.bayes_update(plane[v0:v0 + h, u0:u0 + w], added, self.limits)
                    if informative(added) or (not first and tile.decay.get(lid) != decay_at):
                        tile.version = self.tick()  # the content changed (tile.py: versions)
                    tile.stamp = max(tile.stamp, stamp)
                    if mark is not None:
                        tile.applied[mark[0]] = mark[1]
                    return index
            # Replaced (insert_tile) or removed (discard) since phase 1: the map's tile now.
            tile = self.get_tile(index)
            if tile is None and informative(patch):
                tile = self.get_tile(index, create=True)
        return None

    def _unpin(self, targets: list[Target]) -> None:
        """Pins phase 2 did not release (it raised): released."""
        for target in targets:
            if target.pinned:
                with target.tile.lock:
                    target.tile.pins -= 1
                    target.pinned = False
