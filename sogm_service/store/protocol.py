"""What the service needs of a tile store: the seam a second backend implements.

:class:`~sogm_service.store.directory.DirectoryStore` (one file per tile) and
:class:`~sogm_service.store.s3.S3Store` (one object per tile in an S3 bucket) are the backends
this package ships.  Another one (a database) implements the same methods and keeps the same
guarantees: a write is atomic (a reader sees the old or the new tile, never a mix), a tile that
fails validation is never returned, and :meth:`TileStore.index` lists the tiles present when it
ran.  A *shared* store (:attr:`TileStore.shared`) may be written by other servers too (a
cluster on one bucket): its writes are fenced, and a server never deletes a tile from it
because it stopped owning the tile.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import Protocol

from sogm_service.core.map.tiletypes import LoaderResult, Mark, TileIndex
from sogm_service.wire.tilefile import Expectation, Fixed, StoredTile, TileHeader


@dataclass(frozen=True)
class TileFileInfo:
    """One indexed tile file (its header was checked; its payload is checked on load)."""

    header: TileHeader
    path: PurePath  # a file, or a store's name for its object (``bucket/key``)
    size: int


@dataclass(frozen=True)
class StoreProblem:
    """A file the store refused: where it was, why, and where it went."""

    path: PurePath
    reason: str
    moved_to: PurePath | None


class TileStore(Protocol):
    """Tiles of one map (name, resolution, tile size, frame: :attr:`expect`)."""

    @property
    def expect(self) -> Expectation:
        """What every tile of this store must be (map, resolution, tile size, frame)."""
        ...

    @property
    def shared(self) -> bool:
        """Whether other servers may write this store too (an object store a cluster
        shares): then writes are fenced and ownership never deletes a tile from it."""
        ...

    @property
    def problems(self) -> list[StoreProblem]:
        """Every tile the store refused since it was opened (why, and where it went)."""
        ...

    def index(self) -> dict[TileIndex, TileFileInfo]:
        """Find every stored tile (checking headers, setting bad ones aside)."""
        ...

    def indexed(self) -> dict[TileIndex, TileFileInfo]:
        """The index as last scanned and updated by writes (no I/O)."""
        ...

    def header_for(self, i: int, j: int, layers: Sequence[str], stamp: float,
                   decay: dict[str, float] | None = None,
                   applied: dict[str, Mark] | None = None, version: int = 0) -> TileHeader:
        """The header this store writes for tile ``(i, j)`` (map, frame, datum, ...)."""
        ...

    def load(self, i: int, j: int) -> StoredTile | None:
        """Tile ``(i, j)``, validated, or None when absent or refused."""
        ...

    def loader(self, i: int, j: int) -> LoaderResult | None:
        """:meth:`load` in the shape of :data:`sogm_service.core.map.tiletypes.Loader`."""
        ...

    def read_bytes(self, i: int, j: int) -> bytes | None:
        """Tile ``(i, j)`` in the file format (validated), or None."""
        ...

    def write(self, i: int, j: int, layers: Sequence[str], data: Fixed,
              stamp: float, decay: dict[str, float] | None = None,
              applied: dict[str, Mark] | None = None, version: int = 0) -> TileFileInfo:
        """Encode and atomically store one tile (with its decay stamps, applied marks and
        version, which :meth:`loader` gives back)."""
        ...

    def write_bytes(self, blob: bytes) -> TileFileInfo:
        """Validate a tile in the file format (an import, a replica's copy) and store it."""
        ...

    def remove(self, i: int, j: int) -> bool:
        """Delete tile ``(i, j)``; True when there was one."""
        ...

    def close(self) -> None:
        """Release the store (its lock, connections)."""
        ...
