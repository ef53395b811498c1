"""One tile of the map and the small types around it (:mod:`sogm_service.core.map.tiles` holds the
map that owns them): a tile's planes and bookkeeping, a consistent snapshot of it, the plane
set of a stored stack, and what a fuse keeps of each tile between its two phases.

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
from sogm_service.core.resample import TilePatch


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
            planes.pop(lid, None)  # a repeated name: the last one counts, as it did
    return planes
