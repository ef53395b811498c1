"""Doorway lines: found in walls only, and SEVDS puts a supercell boundary on them."""

from __future__ import annotations

import cv2
import numpy as np

from sogm_service.core.sevds import kernels
from sogm_service.core.sevds.doorways import DOWN, RIGHT, doorway_edges
from sogm_service.core.sevds.segment import SevdsParams, sevds
from sogm_service.eval.metrics import boundary_map


def two_rooms(wall_row: int = 21, thick: int = 2, door: tuple[int, int] = (20, 34)) -> np.ndarray:
    """One occupancy layer 48 x 64: free floor, a horizontal wall of ``thick`` rows at
    ``wall_row`` with a door over columns ``door``, a free-standing table in the lower room."""
    p = np.full((48, 64), 0.05, np.float32)
    p[wall_row:wall_row + thick, :] = 0.95
    p[wall_row:wall_row + thick, door[0]:door[1]] = 0.05
    p[34:38, 10:16] = 0.95  # a table: gaps around it are not doors
    p[34:38, 30:36] = 0.95
    return p[None]


def edges(stack: np.ndarray) -> np.ndarray:
    return doorway_edges(kernels.quantize_hwn(stack, 3), 3)


def test_the_door_line_is_the_walls_middle_across_the_gap() -> None:
    mask = edges(two_rooms())
    rows, cols = np.nonzero(mask & DOWN)
    assert set(rows.tolist()) == {21}  # the upper of the wall's two rows: the edge below it
    assert cols.tolist() == list(range(20, 34))
    assert not (mask & RIGHT).any()  # the gap between the two tables is not in a wall
    vertical = edges(np.ascontiguousarray(two_rooms().transpose(0, 2, 1)))
    np.testing.assert_array_equal(vertical & RIGHT, (mask & DOWN).T * RIGHT)


def test_sevds_cuts_the_doorway_and_not_without_the_term() -> None:
    stack = two_rooms(wall_row=21, thick=1)  # the line lies off the initial 8-cell grid
    door = edges(stack) & DOWN
    rows, cols = np.nonzero(door)

    def cut(p: SevdsParams) -> float:
        """The share of the line's cells with a supercell boundary within one cell (BR's
        tolerance on a map of this size's diagonal)."""
        near = cv2.dilate(boundary_map(sevds(stack, p).labels).astype(np.uint8),
                          np.ones((3, 3), np.uint8))
        return float(np.mean(near[rows, cols] > 0))

    assert cut(SevdsParams()) == 1.0
    assert cut(SevdsParams(doorway=0.0)) < 0.7
