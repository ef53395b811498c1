"""What every tile store shares (:class:`TileStoreBase`): the tiles it expects, its index as last
listed, reading a tile as validated bytes or as a tile, and writing one encoded in the tile
format.  A store (a directory, an S3 bucket) says only where the bytes live: how to list them
(``index``), read one (``_read_valid``), store one (``_store``), remove one and quarantine a bad
one.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Self

from sogm_service.core.geodesy import GeodeticLike, LocalTangentPlane
from sogm_service.core.map.tiletypes import LoaderResult, Mark, TileIndex
from sogm_service.store.protocol import StoreProblem, TileFileInfo
from sogm_service.wire.tilefile import (
    Expectation,
    Fixed,
    StoredTile,
    TileHeader,
    tile_from_bytes,
    tile_header,
    tile_to_bytes,
)


class TileStoreBase:
    """The part of a tile store that does not depend on where the bytes live.

    Thread-safe: ``_lock`` guards ``_index`` (the writer thread writes while the server thread
    indexes and loads)."""

    def __init__(self, map_name: str, resolution: float, tile_size: int, frame: str | None,
                 datum: GeodeticLike | None, level: int, readonly: bool) -> None:
        self.expect = Expectation(map_name, float(resolution), int(tile_size), frame)
        self.level = level
        self.readonly = readonly
        self.plane = None if datum is None else LocalTangentPlane(datum)
        self.problems: list[StoreProblem] = []
        self._lock = threading.RLock()
        self._index: dict[TileIndex, TileFileInfo] = {}

    def close(self) -> None:
        """Release what the store holds (nothing here)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def header_for(self, i: int, j: int, layers: Sequence[str],
                   stamp: float, decay: dict[str, float] | None = None,
                   applied: dict[str, Mark] | None = None, version: int = 0) -> TileHeader:
        """The header this store writes for tile ``(i, j)``."""
        return tile_header(self.expect, i, j, layers, stamp, self.plane, decay, applied, version)

    # -- index ----------------------------------------------------------------------------
    def indexed(self) -> dict[TileIndex, TileFileInfo]:
        """The index as last listed and updated by writes (no I/O)."""
        with self._lock:
            return dict(self._index)

    def __contains__(self, index: object) -> bool:
        with self._lock:
            return index in self._index

    # -- reading --------------------------------------------------------------------------
    def _read_valid(self, i: int, j: int) -> tuple[bytes, StoredTile] | None:
        """Tile ``(i, j)``'s bytes and its validated tile; None when absent or rejected (a
        rejected one quarantined).  Errors of the storage itself propagate."""
        raise NotImplementedError

    def read_bytes(self, i: int, j: int) -> bytes | None:
        """The validated bytes of tile ``(i, j)`` (for ``tiles/<i>/<j>`` replies)."""
        got = self._read_valid(i, j)
        return None if got is None else got[0]

    def load(self, i: int, j: int) -> StoredTile | None:
        """Tile ``(i, j)``, or None when absent or rejected (then quarantined).

        Other errors of the storage (EIO, permissions, an object store's refusal) propagate:
        they may be transient, and answering None would let the caller start an empty tile that
        later overwrites the stored one.
        """
        got = self._read_valid(i, j)
        return None if got is None else got[1]

    def loader(self, i: int, j: int) -> LoaderResult | None:
        """:meth:`load` in the shape of :data:`sogm_service.core.map.tiletypes.Loader`."""
        tile = self.load(i, j)
        return None if tile is None else tile.as_loader_result()

    # -- writing --------------------------------------------------------------------------
    def _store(self, header: TileHeader, blob: bytes) -> TileFileInfo:
        """Store one encoded tile as a whole (never half of it), and index it."""
        raise NotImplementedError

    def write(self, i: int, j: int, layers: Sequence[str], data: Fixed,
              stamp: float, decay: dict[str, float] | None = None,
              applied: dict[str, Mark] | None = None, version: int = 0) -> TileFileInfo:
        """Encode and store one tile (synchronous; :class:`TileWriter
        <sogm_service.store.writer.TileWriter>` runs this).  ``decay``: the decaying layers'
        stamps (:mod:`sogm_service.core.map.forget`); ``applied``: the tile's marks
        (``Tile.applied``); ``version``: the tile's (``Tile.version``)."""
        header = self.header_for(i, j, layers, stamp, decay, applied, version)
        return self._store(header, tile_to_bytes(header, data, self.level))

    def write_bytes(self, blob: bytes) -> TileFileInfo:
        """Validate a tile received from elsewhere (a replica's reply, an import) and store it
        as it is."""
        return self._store(tile_from_bytes(blob, self.expect).header, blob)

