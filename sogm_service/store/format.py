"""Tile files of the store: a file's header read and checked alone (the store's index), and a
whole file read and validated.  The format itself (header, encoding, validation of bytes, file
names) lives in :mod:`sogm_service.wire.tilefile`, the wire format of ``tiles/<i>/<j>`` too, so
that a client decodes tiles without the store.
"""

from __future__ import annotations

import os
from pathlib import Path

from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.tilefile import (
    _PREFIX,
    Expectation,
    StoredTile,
    TileHeader,
    parse_header,
    parse_prefix,
    tile_from_bytes,
)


def read_tile_header(path: Path) -> tuple[TileHeader, int]:
    """Read and check only a file's header; also checks the file length. ``(header, size)``."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        prefix = fh.read(_PREFIX.size)
        _, start = parse_prefix(prefix)
        head = prefix + fh.read(start - len(prefix))
    header, fields, start = parse_header(head)
    expected = start + fields["payload_len"]
    if size != expected:
        what = "truncated" if size < expected else "trailing bytes"
        raise TileFormatError(f"{what}: file is {size} bytes, header says {expected}")
    return header, size


def read_tile_file(path: Path, expect: Expectation | None = None) -> StoredTile:
    """Read and fully validate a tile file."""
    return tile_from_bytes(path.read_bytes(), expect)
