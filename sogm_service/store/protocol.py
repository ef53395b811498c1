"""What the service needs of a tile store: the seam a second backend implements.

:class:`~sogm_service.store.directory.DirectoryStore` (one file per tile) is the backend this
package ships.  Another one (an object store, a database) implements the same methods and keeps
the same guarantees: a write is atomic (a reader sees the old or the new tile, never a mix),
a tile that fails validation is never returned, and :meth:`TileStore.index` lists the tiles
present when it ran.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from sogm_service.core.map.tiletypes import LoaderResult, Mark, TileIndex
from sogm_service.wire.tilefile import Expectation, Fixed, StoredTile, TileHeader


@dataclass(frozen=True)
class TileFileInfo:
    """One indexed tile file (its header was checked; its payload is checked on load)."""

    header: TileHeader
    path: Path
    size: int


@dataclass(frozen=True)
class StoreProblem:
    """A file the store refused: where it was, why, and where it went."""

    path: Path
    reason: str
    moved_to: Path | None


class TileStore(Protocol):
    """Tiles of one map (name, resolution, tile size, frame: :attr:`expect`)."""

    @property
    def expect(self) -> Expectation:
        """What every tile of this store must be (map, resolution, tile size, frame)."""
        ...

    @property
    def problems(self) -> list[StoreProblem]:
        """Every tile the store refused since it was opened (why, and where it went)."""
        ...

    def index(self) -> dict[TileIndex, TileFileInfo]:
        """Find every stored tile (checking headers, setting bad ones aside)."""
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

    def close(self) -> None:
        """Release the store (its lock, connections)."""
        ...
