"""What every job of the tiled map shares (:class:`MapState`): its layers, its tiles and their
residency (created, loaded back through the ``loader`` hook, inserted, evicted, discarded), the
running count of resident bytes, consistent snapshots, the map's clock with the half-lives of
decaying layers (:mod:`sogm_service.core.map.forget`), and the removal of layers
(:meth:`MapState.drop_layers`).

The locks and the rules they follow are described in :mod:`sogm_service.core.map.tiles`; the
fuse (:mod:`sogm_service.core.map.fusing`) and the reads (:mod:`sogm_service.core.map.reading`)
build on this class.  Pure (numpy only, no I/O).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map import forget
from sogm_service.core.map.tile import Tile, TileSnapshot, planes_of
from sogm_service.core.map.tiletypes import Loader, Mark, TileIndex


class MapState:
    """The layers, tiles and clock of a tiled map, and the operations on them that neither fuse
    nor read (:class:`~sogm_service.core.map.tiles.TiledMap` adds those)."""

    def __init__(self, name: str, frame: str, lattice: TileLattice,
                 eps0: float = logodds.DEFAULT_EPS0, loader: Loader | None = None,
                 first_version: int | None = None) -> None:
        self.name = name
        self.frame = frame
        self.lattice = lattice
        self.eps0 = logodds.check_eps0(eps0)
        self.limits = logodds.clamp_limits(eps0)
        self.layers: list[str] = []
        self._layer_index: dict[str, int] = {}
        # Layer index -> name, None once dropped: an index is never reused, so a fuse or read
        # that holds one while its layer is dropped never reaches another layer.
        self._names: list[str | None] = []
        self._retired: dict[str, int] = {}  # a dropped name -> its last index (reads: unknown)
        self._dropping: frozenset[str] = frozenset()  # names a loaded tile leaves out
        self.tiles: dict[TileIndex, Tile] = {}
        self.stored: set[TileIndex] = set()
        self.loader = loader
        self._struct = threading.RLock()
        self._bytes_lock = threading.Lock()
        self._resident_bytes = 0
        # Versions come from one map-wide clock, never per tile: a tile evicted and loaded
        # back must not reuse version numbers that an in-flight save may still confirm.  It
        # starts at the wall clock in microseconds, so a restarted server (with or without a
        # store) never hands out a number an earlier run gave other content (tile.py: versions).
        self._clock = time.time_ns() // 1000 if first_version is None else int(first_version)
        self._clock_lock = threading.Lock()
        self._forget = forget.ForgetRules()
        self._half_lives: dict[int, float | None] = {}
        self._time = -math.inf  # the map's clock: the latest stamp fused or loaded
        self._time_lock = threading.Lock()

    def tick(self) -> int:
        """The next version number (strictly increasing over the map's lifetime)."""
        with self._clock_lock:
            self._clock += 1
            return self._clock

    def _keep_version(self, version: int) -> int:
        """A loaded tile's own version (0: it has none, a new one): the clock moves past it, so
        the tile's next change gets a greater number."""
        if version <= 0:
            return self.tick()
        with self._clock_lock:
            self._clock = max(self._clock, version)
        return version

    # -- layers ---------------------------------------------------------------------------
    def layer_id(self, layer: str, create: bool = False) -> int:
        """Index of ``layer`` in every tile's stack; ``create`` adds it when it is new.  A
        dropped layer (:meth:`drop_layers`) gives its retired index, which no tile has a plane
        of: a read that named it just before the drop reads it as unknown."""
        idx = self._layer_index.get(layer)
        if idx is None:
            if not create:
                retired = self._retired.get(layer)
                if retired is None:
                    raise KeyError(layer)
                return retired
            with self._struct:
                idx = self._layer_index.get(layer)
                if idx is None:
                    idx = len(self._names)
                    self._names.append(layer)
                    self.layers.append(layer)
                    self._layer_index[layer] = idx
        return idx

    def adopt_layers(self, names: Iterable[str]) -> list[int]:
        """Map a stored tile's layer names onto this map's layer indices (adding new ones)."""
        return [self.layer_id(n, create=True) for n in names]

    def drop_layers(self, names: Iterable[str]) -> tuple[list[str], list[TileIndex],
                                                            list[TileIndex]]:
        """Remove layers from the map: ``(layers removed, resident tiles that lost a plane,
        tiles left without any)``.  The tiles that lost a plane get a new version (dirty: the
        caller stores them); a tile left without planes leaves the map, resident and stored
        (the caller removes its file).  Names the map lacks are ignored.

        The indices of removed layers are retired, never reused: a fuse that got one before
        the drop adds into a plane the tile no longer keeps (:meth:`_plane`), so an ISM being
        fused meanwhile is removed with its layer, and a later ISM of the same name starts a
        new layer.  Until :meth:`end_drop`, a tile loaded back (from the store or the
        writer's queue) leaves these layers out and comes back dirty, so the caller rewrites
        the stored tiles one by one with :meth:`get_tile` and :meth:`evict`."""
        with self._struct:
            gone = [n for n in dict.fromkeys(names) if n in self._layer_index]
            retired = {n: self._layer_index.pop(n) for n in gone}
            self._retired.update(retired)
            lids = set(retired.values())
            for n in gone:
                self.layers.remove(n)  # in place: views of the map share the list
            for lid in lids:
                self._names[lid] = None
                self._half_lives.pop(lid, None)
            self._dropping = self._dropping | frozenset(gone)
            rewritten, emptied = [], []
            for index, tile in list(self.tiles.items()):
                with tile.lock:
                    if not self._strip(tile, lids):
                        continue
                    rewritten.append(index)
                    if not tile.planes and not tile.pins:
                        tile.evicted = True
                        del self.tiles[index]
                        self.stored.discard(index)
                        emptied.append(index)
        return gone, rewritten, emptied

    def end_drop(self) -> None:
        """Every stored tile is rewritten: loaded tiles keep all their layers again."""
        with self._struct:
            self._dropping = frozenset()

    def _strip(self, tile: Tile, lids: set[int]) -> bool:
        """Remove the planes of layer indices ``lids`` from ``tile`` (its lock held)."""
        found = [lid for lid in tile.planes if lid in lids]
        for lid in found:
            plane = tile.planes.pop(lid)
            tile.decay.pop(lid, None)
            if self.tiles.get(tile.index) is tile:
                self._account(-plane.nbytes)
        if found:
            tile.version = self.tick()
        return bool(found)

    # -- tiles ----------------------------------------------------------------------------
    @property
    def tile_size(self) -> int:
        return self.lattice.tile_size

    def known_tiles(self) -> set[TileIndex]:
        with self._struct:
            return set(self.tiles) | self.stored

    def not_resident(self) -> list[TileIndex]:
        """The stored tiles that are not resident now, in index order."""
        with self._struct:
            return sorted(self.stored - set(self.tiles))

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
        version = self._keep_version(loaded[5] if len(loaded) > 5 else 0)
        keep = [k for k, n in enumerate(names) if n not in self._dropping]
        if len(keep) < len(names):  # a drop in progress: rewritten without them (dirty)
            names, stack, version = [names[k] for k in keep], stack[keep], self.tick()
        tile = Tile(index, self._planes_for(names, stack), stamp=stamp, version=version,
                    saved_version=version if len(keep) == len(loaded[0]) else -1)
        decay = (loaded[3] if len(loaded) > 3 else None) or {}
        self._adopt_decay(tile, {n: t for n, t in decay.items() if n not in self._dropping})
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
        """A snapshot of version ``version`` of the tile is in the store.  A tile the map no
        longer has (:meth:`discard`, or left empty by :meth:`drop_layers`) stays unknown: a
        snapshot written after it left is the caller's to remove."""
        with self._struct:
            tile = self.tiles.get(index)
            if tile is not None:  # an evicted tile is in ``stored`` already
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
        t = self.tile_size
        out = np.zeros((len(names), t, t), dtype=np.int16)
        for k, name in enumerate(names):
            plane = tile.planes.get(self._layer_index.get(name, -1))
            if plane is not None:
                out[k] = plane
        return names, out

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
        names = self._names
        lids = sorted(lid for lid in tile.planes if names[lid] is not None)
        t = self.tile_size
        data = np.empty((len(lids), t, t), dtype=np.int16)
        for k, lid in enumerate(lids):
            data[k] = tile.planes[lid]
        return TileSnapshot(tile.index, [str(names[lid]) for lid in lids], data, tile.stamp,
                            tile.version, tile.dirty,
                            {str(names[k]): t_d for k, t_d in sorted(tile.decay.items())
                             if k in tile.planes and names[k] is not None},
                            dict(tile.applied))

    def _plane(self, tile: Tile, lid: int,
               fresh: npt.NDArray[np.int16] | None = None) -> npt.NDArray[np.int16]:
        """Tile ``tile``'s plane of layer ``lid``, added (``fresh``, or new zeros) when the
        layer was never written there; counted if the tile is the map's (the caller holds
        ``tile.lock``)."""
        plane = tile.planes.get(lid)
        if plane is None:
            plane = fresh if fresh is not None else self._new_plane()
            if self._names[lid] is None:  # dropped since the fuse began: added, not kept
                return plane
            tile.planes[lid] = plane
            if self.tiles.get(tile.index) is tile:  # not a tile fetched or already gone
                self._account(plane.nbytes)
        return plane

    def _new_plane(self) -> npt.NDArray[np.int16]:
        t = self.tile_size
        return np.zeros((t, t), dtype=np.int16)

    # -- leaving and extent ---------------------------------------------------------------
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
            name = self._names[lid]
            h = self._forget.half_life(name) if self._forget and name is not None else None
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
