"""The tile vocabulary shared by the map, the tile manager and the store (architecture,
section 4: docs/architecture.md#4-maps-and-tiles).

Tile ``(i, j)`` of a lattice with tile size T and resolution r covers
``[i T r, (i+1) T r) x [j T r, (j+1) T r)`` of the map frame and holds every layer as one
``(N, T, T)`` int16 array of fixed-point log-odds.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

TileIndex = tuple[int, int]
"""``(i, j)``: the tile's column and row on the lattice."""

Fixed = npt.NDArray[np.int16]
"""Fixed-point log-odds (:mod:`sogm_service.core.logodds`)."""

Mark = tuple[float, int]
"""An ISM's identity within its key: ``(stamp, digest)`` (a cluster's handover compares them)."""

LoaderResult = (tuple[list[str], Fixed, float]
                | tuple[list[str], Fixed, float, dict[str, float]]
                | tuple[list[str], Fixed, float, dict[str, float], dict[str, Mark]]
                | tuple[list[str], Fixed, float, dict[str, float], dict[str, Mark], int])
"""A tile brought back from storage: ``(layer names, (N, T, T) stack, stamp)``, and for a tile
with decaying layers its decay stamps ``{layer: decayed up to}`` (:mod:`.forget`) as a fourth
item, and for a tile with applied marks (the last ISM fused into it per ISM key, ``Tile.applied``)
those as a fifth (the fourth then ``{}`` when nothing decays), and the tile's version
(``Tile.version``, kept across a store) as a sixth.  Items are added at the end so
that loaders of the shorter shapes keep working."""

Loader = Callable[[int, int], LoaderResult | None]
"""Brings back tile ``(i, j)`` that is not resident, or None when there is none."""


def tile_token(i: int, j: int) -> str:
    """The lattice index as it appears in tile names and file names: ``i+0003_j-0012``.

    Signed and zero-padded so that ``ls`` sorts a row of tiles in order (for |i| < 10000).
    """
    return f"i{i:+05d}_j{j:+05d}"


def tile_name(map_name: str, i: int, j: int) -> str:
    """The name of a tile's frame, e.g. ``default/tile_i+0003_j-0012`` (unique per map)."""
    return f"{map_name}/tile_{tile_token(i, j)}"
