"""Which part of a published grid changed: the rectangles of ``map_msgs/msg/OccupancyGridUpdate``
(pure, no zenoh).

:func:`changed_rects` compares the grid about to be published with the last one sent on the
same extent.  The grid is cut into square blocks (``block`` cells, aligned with the grid's cell
(0, 0), which :func:`~sogm_service.adapters.ros2.views.stable_extent` keeps on the map's tile
lattice); in each row of blocks every run of changed blocks gives one rectangle, shrunk to the
changed cells inside it.  The rectangles cover every changed cell and no two overlap, so a
subscriber that writes them into its last full grid holds the new grid, in any order.  When a
change is scattered into more than ``max_rects`` runs, each row of blocks gives one rectangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sogm_service.adapters.ros2.cdr import GridUpdateFields, OccupancyGridFields

DEFAULT_BLOCK = 64  # cells: a quarter of the default tile edge
DEFAULT_MAX_RECTS = 64  # updates sent for one grid in one period


@dataclass(frozen=True, slots=True)
class Rect:
    """Cells ``[x, x + width) x [y, y + height)`` of a grid (``x``: column, ``y``: row)."""

    x: int
    y: int
    width: int
    height: int

    @property
    def cells(self) -> int:
        return self.width * self.height


def _tight(diff: npt.NDArray[np.bool_], x0: int, y0: int) -> Rect:
    """The bounding rectangle of the changed cells of ``diff`` (a block at ``(x0, y0)``)."""
    rows = np.flatnonzero(diff.any(axis=1))
    cols = np.flatnonzero(diff.any(axis=0))
    return Rect(x0 + int(cols[0]), y0 + int(rows[0]), int(cols[-1] - cols[0] + 1),
                int(rows[-1] - rows[0] + 1))


def _runs(flags: npt.NDArray[np.bool_]) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of True in a 1-D array."""
    padded = np.concatenate(([False], flags, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def changed_rects(old: npt.NDArray[np.int8], new: npt.NDArray[np.int8], *,
                  block: int = DEFAULT_BLOCK,
                  max_rects: int = DEFAULT_MAX_RECTS) -> list[Rect]:
    """Rectangles covering every cell where ``new`` differs from ``old`` (same shape)."""
    if old.shape != new.shape:
        raise ValueError(f"grids of shapes {old.shape} and {new.shape}")
    if block <= 0:
        raise ValueError(f"block must be positive, got {block}")
    diff = old != new
    if not diff.any():
        return []
    h, w = diff.shape
    nby, nbx = -(-h // block), -(-w // block)
    padded = np.zeros((nby * block, nbx * block), dtype=bool)
    padded[:h, :w] = diff
    blocks = np.asarray(padded.reshape(nby, block, nbx, block).any(axis=(1, 3)), dtype=bool)
    rows = [by for by in range(nby) if blocks[by].any()]
    runs = [(by, run) for by in rows for run in _runs(blocks[by])]
    if len(runs) > max_rects:  # scattered: one rectangle per row of blocks
        runs = [(by, (0, nbx)) for by in rows]
    out = []
    for by, (b0, b1) in runs:
        y0, x0 = by * block, b0 * block
        out.append(_tight(diff[y0:y0 + block, x0:min(w, b1 * block)], x0, y0))
    return out


def grid_update(grid: OccupancyGridFields, rect: Rect) -> GridUpdateFields:
    """The update that writes ``rect`` of ``grid`` into a subscriber's copy."""
    data = grid.data[rect.y:rect.y + rect.height, rect.x:rect.x + rect.width]
    return GridUpdateFields(grid.frame, grid.stamp, rect.x, rect.y, rect.width, rect.height,
                            np.ascontiguousarray(data))


def apply_update(data: npt.NDArray[np.int8], u: GridUpdateFields) -> bool:
    """Write an update into ``data`` (``(height, width)``, in place), as nav2's static layer
    does; False (nothing written) when the rectangle is not inside the grid."""
    h, w = data.shape
    if u.x < 0 or u.y < 0 or u.x + u.width > w or u.y + u.height > h:
        return False
    data[u.y:u.y + u.height, u.x:u.x + u.width] = u.data
    return True
