"""One tile of the map and the small types around it (:mod:`sogm_service.core.map.tiles` holds the
map that owns them): a tile's planes and bookkeeping, a consistent snapshot of it, which tiles a
fuse may write, and the plane set of a stored stack.

**Versions** (``Tile.version``): one number per state of a tile's content, from the map-wide
clock (:meth:`MapState.tick`), which also tells a dirty tile (``version != saved_version``) and
lets a client ask what changed since the version it holds (``tiles/changed``).

* It moves exactly when the tile's content (its planes) changes: a fuse bumps it when its patch
  into the tile has a non-zero increment, or when it decayed a layer in place; a fuse of all
  unknown cells there changes nothing and leaves it.  A non-zero increment that the clamp absorbs
  entirely still bumps it: telling would cost a copy of the block, and the fuse's second phase
  allocates nothing.  A spurious bump costs a client one tile's download, never a stale copy.
* A tile created, inserted (a replica, a handover) or loaded without a version gets a new one; a
  tile loaded back from the store keeps its own (the ``tile_version`` header field), and the
  clock moves past it.  The clock starts at the wall clock in microseconds, so a restarted server
  never reuses a number (it ticks far less than once a microsecond).
* A decaying layer (:mod:`sogm_service.core.map.forget`) is content as the tile holds it: its
  planes and decay stamps, which its reads decay to the map's clock on the fly.  The clock's
  advance alone does not move the version (the decayed read is a function of the stored state
  and the time asked for); a write that decays the layer in place does.

Pure (numpy only, no I/O).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from sogm_service.core.map.tiletypes import Mark, TileIndex


@dataclass(eq=False)
class Tile:
    """One tile: its planes (layer index -> ``(T, T)`` int16; a layer never written here has
    none: all unknown) and bookkeeping.

    ``lock`` guards ``planes`` (the dict and the arrays), ``stamp`` and the versions;
    ``evicted`` is set (under it) when the tile leaves the map, so a writer holding a stale
    reference fetches the tile again.
    """

    index: TileIndex
    planes: dict[int, npt.NDArray[np.int16]] = field(default_factory=dict)
    stamp: float = 0.0
    version: int = 0
    saved_version: int = -1
    last_used: float = field(default_factory=time.monotonic)
    evicted: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # Decaying layers (:mod:`sogm_service.core.map.forget`): layer index -> the time up to which
    # its cells are decayed (absent: the tile's ``stamp``).  Guarded by ``lock``.
    decay: dict[int, float] = field(default_factory=dict)
    applied: dict[str, Mark] = field(default_factory=dict, repr=False)
    """The last ISM fused here per ISM key (a cluster's handover uses it); stored with the
    tile (the ``applied`` header field) and adopted again when it is loaded back."""
    pins: int = 0
    """Fuses that hold this tile between their two phases (:meth:`TiledMap.fuse`); a pinned
    tile is not evicted.  Guarded by ``lock``."""

    @property
    def dirty(self) -> bool:
        return self.version != self.saved_version

    @property
    def nbytes(self) -> int:
        """Bytes of the planes (the layers written into this tile)."""
        return sum(int(p.nbytes) for p in list(self.planes.values()))

    def stack(self, n: int, tile_size: int) -> npt.NDArray[np.int16]:
        """A new ``(n, T, T)`` array of layers ``0..n-1``, zeros where a plane is absent (the
        caller holds ``lock`` or has the tile to itself)."""
        out = np.zeros((n, tile_size, tile_size), dtype=np.int16)
        for lid, plane in self.planes.items():
            if lid < n:
                out[lid] = plane
        return out


@dataclass(frozen=True)
class TileSnapshot:
    """A consistent copy of one tile: the names of the layers it has a plane of (in the map's
    order), their ``(n, T, T)`` data, stamp and version, and whether that version was not
    stored yet."""

    index: TileIndex
    layers: list[str]
    data: npt.NDArray[np.int16]
    stamp: float
    version: int
    dirty: bool
    decay: dict[str, float] = field(default_factory=dict)  # decaying layer -> decayed up to
    applied: dict[str, Mark] = field(default_factory=dict)


Owner = Callable[[TileIndex], bool]
"""Which tiles a call may write (a fuse worker's share of the lattice)."""


def planes_of(ids: list[int], stack: npt.NDArray[np.int16],
              limits: tuple[int, int] | None = None) -> dict[int, npt.NDArray[np.int16]]:
    """``stack[k]`` as the plane of layer ``ids[k]`` (each its own array; clipped to
    ``limits`` if given), all-zero layers left out (absent means unknown)."""
    planes: dict[int, npt.NDArray[np.int16]] = {}
    for k, lid in enumerate(ids):
        plane = np.array(stack[k], dtype=np.int16) if limits is None \
            else np.clip(stack[k], np.int16(limits[0]), np.int16(limits[1])).astype(np.int16,
                                                                                 copy=False)
        if plane.any():
            planes[lid] = plane
        else:
            planes.pop(lid, None)  # a repeated name: the last one counts
    return planes
