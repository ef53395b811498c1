"""The tiled semantic map: a stack of log-odds layers kept in tiles of a fixed lattice.

Architecture, section 4 (docs/architecture.md#4-maps-and-tiles):
tile ``(i, j)`` holds its layers as ``(T, T)`` int16 planes of fixed-point
log-odds (:mod:`sogm_service.core.logodds`), one per layer written into that tile, allocated on
the layer's first write there (an absent plane is all unknown, 0): adding a layer costs one
plane in the tiles it reaches, never a copy of other layers.  A layer is added to the
map when its first ISM arrives; tiles are created on first write.  Writing an ISM resamples it
straight into each tile it overlaps (no map-sized intermediate), so the cost is proportional to
the ISM's footprint.

Concurrency: the map is shared by ingestion workers, queries and checkpoints without a
map-wide lock, so a query never waits for an ISM to be fused.

* Every tile has its own lock, held only to add one tile's patch (Eq. 1), to copy a block out
  of it, or to snapshot it; the resampling of an ISM (the expensive part) runs without any lock.
  A reader sees each tile either before or after an ISM's patch, never halfway; an ISM that
  spans several tiles may be visible in one and not yet in the next for the duration of its
  fuse.
* A structure lock guards the tile dictionary, the stored set and the layer list: creating,
  loading, inserting and evicting tiles, adding layers.  It is never held while a tile's lock
  is awaited by a writer, so it cannot deadlock with them.
* Writers to one tile are serialised by its lock; callers that need a tile's ISMs applied in
  arrival order (the service's fuse workers own disjoint tiles) keep that order themselves.
* A fuse is transactional, in two phases (:meth:`TiledMap.fuse`): first every patch is
  computed and every tile got, created or loaded back and *pinned* (a pinned tile is not
  evicted), then the patches are added, each under its tile's lock only.  A failure in the
  first phase changes no tile: the tiles it created or loaded leave the map again.

This module is pure (no I/O): persistence and the memory budget are the caller's business
through two hooks, ``loader`` (bring back a tile that is not resident) and the LRU order of
:meth:`TiledMap.least_recently_used`.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterable

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice, wrap_angle
from sogm_service.core.map import forget, gather
from sogm_service.core.map.footprint import gather_taps, prefer_gather
from sogm_service.core.map.tile import Owner, Target, Tile, TileSnapshot, planes_of, scratch
from sogm_service.core.map.tiletypes import Loader, TileIndex
from sogm_service.core.map.tiletypes import Mark as Mark  # re-exported (its home before)
from sogm_service.core.resample import (
    Interp,
    TilePatch,
    dst_to_src,
    informative,
    resample_stack,
    tile_patches,
)

__all__ = ["Mark", "Owner", "Tile", "TileSnapshot", "TiledMap", "planes_of"]

_ALIGN_TOL = 1e-6


class TiledMap:
    """Semantic layers on a tile lattice, fused with Eq. 1 and sampled with Eq. 3-5."""

    def __init__(self, name: str, frame: str, lattice: TileLattice,
                 eps0: float = logodds.DEFAULT_EPS0, loader: Loader | None = None) -> None:
        self.name = name
        self.frame = frame
        self.lattice = lattice
        self.eps0 = logodds.check_eps0(eps0)
        self.limits = logodds.clamp_limits(eps0)
        self.layers: list[str] = []
        self._layer_index: dict[str, int] = {}
        self.tiles: dict[TileIndex, Tile] = {}
        self.stored: set[TileIndex] = set()
        self.loader = loader
        self._struct = threading.RLock()
        self._bytes_lock = threading.Lock()
        self._resident_bytes = 0
        # Versions come from one map-wide clock, never per tile: a tile evicted and loaded
        # back must not reuse version numbers that an in-flight save may still confirm.
        self._clock = itertools.count(1)
        self._forget = forget.ForgetRules()
        self._half_lives: dict[int, float | None] = {}
        self._time = -math.inf  # the map's clock: the latest stamp fused or loaded
        self._time_lock = threading.Lock()

    def tick(self) -> int:
        """The next version number (strictly increasing over the map's lifetime)."""
        return next(self._clock)

    # -- layers ---------------------------------------------------------------------------
    def layer_id(self, layer: str, create: bool = False) -> int:
        """Index of ``layer`` in every tile's stack; ``create`` adds it when it is new."""
        idx = self._layer_index.get(layer)
        if idx is None:
            if not create:
                raise KeyError(layer)
            with self._struct:
                idx = self._layer_index.get(layer)
                if idx is None:
                    idx = len(self.layers)
                    self.layers.append(layer)
                    self._layer_index[layer] = idx
        return idx

    def adopt_layers(self, names: Iterable[str]) -> list[int]:
        """Map a stored tile's layer names onto this map's layer indices (adding new ones)."""
        return [self.layer_id(n, create=True) for n in names]

    # -- tiles ----------------------------------------------------------------------------
    @property
    def tile_size(self) -> int:
        return self.lattice.tile_size

    def known_tiles(self) -> set[TileIndex]:
        with self._struct:
            return set(self.tiles) | self.stored

    def resident(self) -> list[Tile]:
        """The resident tiles now (a copy of the list: safe to iterate while others write)."""
        with self._struct:
            return list(self.tiles.values())

    def resident_bytes(self) -> int:
        """Bytes of the resident tiles' stacks: a running count (admission reads it per ISM)."""
        return self._resident_bytes

    def _account(self, delta: int) -> None:
        with self._bytes_lock:
            self._resident_bytes += delta

    def get_tile(self, index: TileIndex, create: bool = False) -> Tile | None:
        """The tile at ``index``, loading it back if it was evicted; ``create`` makes it."""
        tile = self.tiles.get(index)
        if tile is None and (create or index in self.stored):
            with self._struct:
                tile = self.tiles.get(index)
                if tile is None and index in self.stored and self.loader is not None:
                    tile = self._load(index)
                if tile is None and create:
                    tile = Tile(index, version=self.tick())  # no planes yet: 0 bytes
                    self.tiles[index] = tile
        if tile is not None:
            tile.last_used = time.monotonic()
        return tile

    def _load(self, index: TileIndex) -> Tile | None:
        assert self.loader is not None
        loaded = self.loader(*index)
        if loaded is None:
            self.stored.discard(index)
            return None
        names, stack, stamp = loaded[0], loaded[1], loaded[2]
        version = self.tick()
        tile = Tile(index, self._planes_for(names, stack), stamp=stamp, version=version,
                    saved_version=version)
        self._adopt_decay(tile, loaded[3] if len(loaded) > 3 else None)
        if len(loaded) > 4:
            tile.applied = dict(loaded[4])
        self.tiles[index] = tile
        self._account(tile.nbytes)
        return tile

    def _planes_for(self, names: list[str], stack: npt.NDArray[np.int16]
                    ) -> dict[int, npt.NDArray[np.int16]]:
        """A stored stack as planes in this map's layer indices (all-zero layers left out: they
        cost nothing).  Clamped: a tile stored under a wider clamp (another eps0) or damaged
        would otherwise break the invariant Eq. 1's add-then-clip relies on."""
        return planes_of(self.adopt_layers(names), stack, self.limits)

    def insert_tile(self, index: TileIndex, names: list[str], stack: npt.NDArray[np.int16],
                    stamp: float, saved: bool,
                    decay: dict[str, float] | None = None,
                    applied: dict[str, Mark] | None = None) -> Tile:
        """Put a whole tile in place (from a store or a replica), replacing what was there."""
        t = self.tile_size
        if stack.shape != (len(names), t, t):
            raise ValueError(f"tile stack shape {stack.shape} != {(len(names), t, t)}")
        with self._struct:
            version = self.tick()
            tile = Tile(index, self._planes_for(names, stack), stamp=stamp, version=version,
                        saved_version=version if saved else -1, applied=dict(applied or {}))
            self._adopt_decay(tile, decay)
            old = self.tiles.get(index)
            if old is not None:
                with old.lock:
                    old.evicted = True
                    self._account(-old.nbytes)
            self.tiles[index] = tile
            self._account(tile.nbytes)
        return tile

    def evict(self, index: TileIndex,
              before: Callable[[TileSnapshot], None] | None = None) -> Tile | None:
        """Drop a resident tile from memory.  ``before`` gets its last snapshot first, taken
        with the tile locked (so no write can slip in between; the caller stores it).  None:
        not resident, or pinned by a fuse in progress (it stays)."""
        with self._struct:
            tile = self.tiles.get(index)
            if tile is None:
                return None
            with tile.lock:
                if tile.pins:  # a fuse between its phases (see fuse): stays, for now
                    return None
                if before is not None:
                    before(self._snapshot_locked(tile))
                tile.evicted = True
                del self.tiles[index]
                self._account(-tile.nbytes)
            self.stored.add(index)
        return tile

    def mark_saved(self, index: TileIndex, version: int) -> None:
        """A snapshot of version ``version`` of the tile is in the store."""
        with self._struct:
            tile = self.tiles.get(index)
            self.stored.add(index)
        if tile is not None:
            with tile.lock:
                tile.saved_version = max(tile.saved_version, version)

    def least_recently_used(self) -> list[TileIndex]:
        with self._struct:
            tiles = list(self.tiles.values())
        return [t.index for t in sorted(tiles, key=lambda t: t.last_used)]

    def tile_layers(self, tile: Tile) -> tuple[list[str], npt.NDArray[np.int16]]:
        """``(layer names, (n, T, T) stack)`` of a tile in the map's layers, zeros where the
        tile has no plane: a new array (the caller holds the tile's lock, or has the map to
        itself)."""
        names = list(self.layers)
        return names, tile.stack(len(names), self.tile_size)

    def snapshot(self, index: TileIndex) -> TileSnapshot | None:
        """A consistent copy of a resident tile (None when it is not resident)."""
        tile = self.tiles.get(index)
        if tile is None:
            return None
        with tile.lock:
            return None if tile.evicted else self._snapshot_locked(tile)

    def _snapshot_locked(self, tile: Tile) -> TileSnapshot:
        """Sparse: the layers this tile has a plane of, in the map's order (a tile of one
        layer in a map of a thousand copies one plane; the store and replicas carry layer
        names per tile)."""
        lids = sorted(tile.planes)
        t = self.tile_size
        data = np.empty((len(lids), t, t), dtype=np.int16)
        for k, lid in enumerate(lids):
            data[k] = tile.planes[lid]
        return TileSnapshot(tile.index, [self.layers[lid] for lid in lids], data, tile.stamp,
                            tile.version, tile.dirty,
                            {self.layers[k]: t_d for k, t_d in sorted(tile.decay.items())
                             if k in tile.planes},
                            dict(tile.applied))

    def _plane(self, tile: Tile, lid: int,
               fresh: npt.NDArray[np.int16] | None = None) -> npt.NDArray[np.int16]:
        """Tile ``tile``'s plane of layer ``lid``, added (``fresh``, or new zeros) when the
        layer was never written there; counted if the tile is the map's (the caller holds
        ``tile.lock``)."""
        plane = tile.planes.get(lid)
        if plane is None:
            plane = fresh if fresh is not None else self._new_plane()
            tile.planes[lid] = plane
            if self.tiles.get(tile.index) is tile:  # not a tile fetched or already gone
                self._account(plane.nbytes)
        return plane

    def _new_plane(self) -> npt.NDArray[np.int16]:
        t = self.tile_size
        return np.zeros((t, t), dtype=np.int16)

    # -- writing --------------------------------------------------------------------------
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

    # -- reading --------------------------------------------------------------------------
    def mosaic(self, box: tuple[int, int, int, int], layer_ids: list[int],
               now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layer_ids), h, w)`` log-odds of the map-cell box ``(c0, r0, w, h)``;
        decaying layers as they are at ``now`` (default: :meth:`now`)."""
        c0, r0, w, h = box
        now = self.now() if now is None else now
        t = self.tile_size
        out = np.zeros((len(layer_ids), h, w), dtype=np.int16)
        for j in range(r0 // t, (r0 + h - 1) // t + 1):
            for i in range(c0 // t, (c0 + w - 1) // t + 1):
                tile = self.get_tile((i, j))  # loads an evicted tile back; a read is a use
                if tile is not None:
                    self._copy_block(tile, (i, j), box, layer_ids, out, now)
        return out

    def _copy_block(self, tile: Tile, index: TileIndex, box: tuple[int, int, int, int],
                    layer_ids: list[int], out: npt.NDArray[np.int16],
                    now: float = -math.inf) -> None:
        c0, r0, w, h = box
        t = self.tile_size
        tc, tr = index[0] * t, index[1] * t
        a0, a1 = max(c0, tc), min(c0 + w, tc + t)
        b0, b1 = max(r0, tr), min(r0 + h, tr + t)
        with tile.lock:  # an evicted tile still holds its last state: a consistent read
            for k, lid in enumerate(layer_ids):
                plane = tile.planes.get(lid)
                if plane is not None:  # else unknown: out is zeros already
                    out[k, b0 - r0:b1 - r0, a0 - c0:a1 - c0] = \
                        plane[b0 - tr:b1 - tr, a0 - tc:a1 - tc]
                    self._decay_for_read(tile, lid, out[k, b0 - r0:b1 - r0, a0 - c0:a1 - c0],
                                         now)

    def sample(self, window: GridGeometry, layers: list[str],
               interp: Interp = "biodds", now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layers), H, W)`` fixed log-odds of the map resampled into ``window``.

        Unknown area (no tile, or outside every ISM so far) is 0.  Raises ``KeyError`` for a
        layer the map does not have.
        """
        ids = [self.layer_id(n) for n in layers]
        res = self.lattice.resolution
        xmin, ymin, xmax, ymax = window.bounds()
        # One cell of margin each side so that bilinear reads real neighbours at the edge.
        c0, r0 = math.floor(xmin / res) - 1, math.floor(ymin / res) - 1
        c1, r1 = math.ceil(xmax / res) + 1, math.ceil(ymax / res) + 1
        box = (c0, r0, c1 - c0, r1 - r0)
        if prefer_gather(gather_taps(interp) * window.width * window.height, box[2] * box[3]):
            return self.gather(window, ids, box, interp, now)  # coarse: read only the taps
        src = self.mosaic(box, ids, now)
        src_geom = GridGeometry(res, box[2], box[3], Pose2D(c0 * res, r0 * res, 0.0))
        if _is_aligned(src_geom, window):
            du, dv = _cell_offset(src_geom, window)
            return np.ascontiguousarray(src[:, dv:dv + window.height, du:du + window.width])
        return resample_stack(src, src_geom, window, interp)

    def discard(self, index: TileIndex) -> bool:
        """Forget a tile entirely (resident and stored): a cluster member that no longer
        owns it.  The caller removes its file from the store."""
        with self._struct:
            tile = self.tiles.get(index)
            known = tile is not None or index in self.stored
            self.stored.discard(index)
            if tile is not None:
                with tile.lock:  # leaves the map and the count in one step
                    del self.tiles[index]
                    tile.evicted = True
                    self._account(-tile.nbytes)
        return known

    def bounds(self, known: set[TileIndex] | None = None
               ) -> tuple[float, float, float, float] | None:
        """Metric box ``(xmin, ymin, xmax, ymax)`` of every tile the map has (or of
        ``known``)."""
        if known is None:
            known = self.known_tiles()
        if not known:
            return None
        span = self.lattice.span
        ii = [i for i, _ in known]
        jj = [j for _, j in known]
        return (min(ii) * span, min(jj) * span, (max(ii) + 1) * span, (max(jj) + 1) * span)

    # -- forgetting (:mod:`sogm_service.core.map.forget`) ----------------------------
    def set_forget(self, rules: dict[str, float] | forget.ForgetRules) -> None:
        """Which layers decay toward unknown, with which half-life (seconds): ``{layer name
        or fnmatch pattern: half-life}``.  Set it before the map is used."""
        self._forget = rules if isinstance(rules, forget.ForgetRules) \
            else forget.ForgetRules(rules)
        self._half_lives = {}

    def half_life(self, lid: int) -> float | None:
        """The half-life of layer index ``lid`` (None: it never forgets)."""
        try:
            return self._half_lives[lid]
        except KeyError:
            h = self._forget.half_life(self.layers[lid]) if self._forget else None
            self._half_lives[lid] = h
            return h

    def now(self) -> float:
        """The map's clock: the latest ISM stamp fused (or tile stamp loaded); reads decay
        to it by default.  ``-inf`` before any."""
        return self._time

    def advance_clock(self, t: float) -> None:
        """Move the map's clock forward to ``t`` (never back): e.g. a service that wants an
        idle map to keep forgetting advances it with its own clock."""
        if t > self._time:
            with self._time_lock:
                if t > self._time:
                    self._time = float(t)

    def _adopt_decay(self, tile: Tile, decay: dict[str, float] | None) -> None:
        """A loaded or inserted tile's decay stamps (names) in this map's layer indices."""
        self.advance_clock(tile.stamp)
        for name, t in (decay or {}).items():
            lid = self.layer_id(name, create=True)
            tile.decay[lid] = float(t)
            self.advance_clock(t)

    def _decay_for_read(self, tile: Tile, lid: int, block: npt.NDArray[np.int16],
                        now: float) -> None:
        """A copied block of a decaying layer as it is at ``now`` (``tile.lock`` held)."""
        h = self.half_life(lid)
        if h is not None:
            forget.for_read(tile, lid, h, block, now)

    # -- the gather path of coarse windows (:mod:`sogm_service.core.map.gather`) ----------------
    def gather(self, window: GridGeometry, layer_ids: list[int], box: tuple[int, int, int, int],
               interp: Interp = "biodds", now: float | None = None) -> npt.NDArray[np.int16]:
        """What :meth:`sample` returns for ``window`` (map-cell ``box`` its full path would
        build), reading only the cells the warp would interpolate from (1 or 4 per output
        cell) instead of the whole box."""
        c0, r0, bw, bh = box
        res = self.lattice.resolution
        src_geom = GridGeometry(res, bw, bh, Pose2D(c0 * res, r0 * res, 0.0))
        taps = gather.taps(dst_to_src(src_geom, window)[:2], bw, bh, window.width,
                           window.height, interp)
        values = np.zeros((len(layer_ids), *taps.u.shape), dtype=np.int16)
        values[:, taps.inside] = self.read_cells(taps.u[taps.inside] + c0,
                                                 taps.v[taps.inside] + r0, layer_ids, now)
        return gather.combine(values, taps, interp)

    def read_cells(self, u: npt.NDArray[np.int64], v: npt.NDArray[np.int64],
                   layer_ids: list[int], now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layer_ids), n)`` log-odds of the map cells ``(u[k], v[k])`` (0 where there
        is no tile), decaying layers as at ``now``: :meth:`mosaic` for scattered cells, tile
        by tile under each tile's lock."""
        now = self.now() if now is None else now
        t = self.tile_size
        out = np.zeros((len(layer_ids), u.size), dtype=np.int16)
        if u.size == 0:
            return out
        ti, tj = u // t, v // t
        order = np.lexsort((ti, tj))
        ti_s, tj_s = ti[order], tj[order]
        starts = np.flatnonzero(np.r_[True, (ti_s[1:] != ti_s[:-1]) | (tj_s[1:] != tj_s[:-1])])
        ends = np.r_[starts[1:], order.size]
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            index = (int(ti_s[a]), int(tj_s[a]))
            tile = self.get_tile(index)  # loads an evicted tile back; a read is a use
            if tile is None:
                continue
            sel = order[a:b]
            lu, lv = u[sel] - index[0] * t, v[sel] - index[1] * t
            with tile.lock:  # as _copy_block: an evicted tile still holds its last state
                for k, lid in enumerate(layer_ids):
                    plane = tile.planes.get(lid)
                    if plane is not None:  # else unknown: out is zeros already
                        cells = plane[lv, lu]  # a copy (fancy indexing)
                        self._decay_for_read(tile, lid, cells, now)
                        out[k, sel] = cells
        return out

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
                    age = 1.0 if half_life is None else forget.before_write(
                        tile, lid, half_life, stamp, first, work)
                    added = patch if age == 1.0 else forget.aged(patch, age, work)
                    logodds.bayes_update(plane[v0:v0 + h, u0:u0 + w], added, self.limits)
                    tile.version = self.tick()
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


def _is_aligned(src: GridGeometry, dst: GridGeometry) -> bool:
    """Same resolution and heading, and ``dst`` starts on a cell corner of ``src``."""
    if abs(src.resolution - dst.resolution) > _ALIGN_TOL * src.resolution:
        return False
    if abs(wrap_angle(dst.origin.yaw - src.origin.yaw)) > 1e-9:
        return False
    m = src.world_to_cell() @ dst.cell_to_world()
    return bool(np.all(np.abs(m[:2, 2] - np.rint(m[:2, 2])) < _ALIGN_TOL))


def _cell_offset(src: GridGeometry, dst: GridGeometry) -> tuple[int, int]:
    m = src.world_to_cell() @ dst.cell_to_world()
    return int(np.rint(m[0, 2])), int(np.rint(m[1, 2]))
