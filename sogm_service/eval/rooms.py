"""Labelled room maps: floor plans whose rooms are the ground truth of a room segmentation.

:func:`room_scene` draws a randomised office floor (seeded) the way a 2D SLAM map of a building
looks: one occupancy layer, unknown (p = 0.5) outside the building, walls and furniture occupied,
floor free.  The ground truth is what a person labelling the map's rooms draws: every room's
floor (its doorway included, cut at the wall's middle line) is one class, walls and furniture
another, the outside a third.  UE and BR are measured on the 4-connected components of those
classes (:func:`sogm_service.eval.scenes.gt_segments`).

The plan: the building's interior is cut recursively (a binary space partition) into rooms of
at least ``min_room`` cells a side, each cut a wall of 1-3 cells with one door of 10-18 cells;
the outer wall is 1-3 cells.  Each room gets up to four pieces of furniture (3-14 cells), some
against a wall; a few wall cells are ragged (one cell into the room, as laser maps are); up to
19 patches of 5-19 cells of floor stay unobserved (p = 0.5, still their room's in the ground
truth, as a person labels a room's unexplored corner).  Occupied cells read 0.95, free 0.05,
unknown 0.5, with Gaussian noise of a standard deviation drawn per map from 0.02-0.08 (clipped).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from sogm_service.eval.scenes import Scene

ROOM_CLASSES: tuple[str, ...] = ("unknown", "wall")
"""Classes 0 and 1; rooms are the classes from 2 on (named ``room1``, ``room2``, ...)."""

_Box = tuple[int, int, int, int]  # row0, col0, row1, col1 (exclusive ends)


def _split(rng: np.random.Generator, box: _Box, min_room: int, occ: npt.NDArray[np.bool_],
           rooms: list[_Box], depth: int) -> None:
    """Cut ``box`` into rooms: a wall across its longer side with a door, then recurse."""
    r0, c0, r1, c1 = box
    h, w = r1 - r0, c1 - c0
    along_rows = h > w if h != w else bool(rng.integers(2))
    side = h if along_rows else w
    if side < 2 * min_room + 2 or (depth >= 2 and rng.random() < 0.25):
        rooms.append(box)
        return
    t = int(rng.integers(1, 4))
    cut = int(rng.integers(min_room, side - min_room - t + 1))
    span = w if along_rows else h
    door = int(rng.integers(10, 19))
    d0 = int(rng.integers(3, max(4, span - door - 3)))
    if along_rows:
        occ[r0 + cut:r0 + cut + t, c0:c1] = True
        occ[r0 + cut:r0 + cut + t, c0 + d0:c0 + d0 + door] = False
        first, second = (r0, c0, r0 + cut, c1), (r0 + cut + t, c0, r1, c1)
    else:
        occ[r0:r1, c0 + cut:c0 + cut + t] = True
        occ[r0 + d0:r0 + d0 + door, c0 + cut:c0 + cut + t] = False
        first, second = (r0, c0, r1, c0 + cut), (r0, c0 + cut + t, r1, c1)
    # The doorway's cells belong to the room on either side of the wall's middle line.
    half = t // 2
    if along_rows:
        first = (r0, c0, r0 + cut + half, c1)
        second = (r0 + cut + half, c0, r1, c1)
    else:
        first = (r0, c0, r1, c0 + cut + half)
        second = (r0, c0 + cut + half, r1, c1)
    _split(rng, first, min_room, occ, rooms, depth + 1)
    _split(rng, second, min_room, occ, rooms, depth + 1)


def _furniture(rng: np.random.Generator, box: _Box, occ: npt.NDArray[np.bool_]) -> None:
    r0, c0, r1, c1 = box
    for _ in range(int(rng.integers(0, 5))):
        fh, fw = (int(v) for v in rng.integers(3, 15, size=2))
        if r1 - r0 < fh + 8 or c1 - c0 < fw + 8:
            continue
        if rng.random() < 0.5:  # against the room's first wall
            r, c = r0 + 1, int(rng.integers(c0 + 4, c1 - fw - 3))
        else:
            r, c = int(rng.integers(r0 + 4, r1 - fh - 3)), int(rng.integers(c0 + 4, c1 - fw - 3))
        occ[r:r + fh, c:c + fw] = True


def room_scene(seed: int, height: int = 300, width: int = 400, min_room: int = 40) -> Scene:
    """A labelled room map (module docstring): one ``occupancy`` layer and its room classes."""
    rng = np.random.default_rng([seed, 0x2009])
    margin = int(rng.integers(6, 16))
    wall = int(rng.integers(1, 4))
    known = np.zeros((height, width), bool)
    known[margin:height - margin, margin:width - margin] = True
    occ = known.copy()
    inner: _Box = (margin + wall, margin + wall, height - margin - wall, width - margin - wall)
    occ[inner[0]:inner[2], inner[1]:inner[3]] = False
    rooms: list[_Box] = []
    _split(rng, inner, min_room, occ, rooms, 0)
    for box in rooms:
        _furniture(rng, box, occ)
    free = known & ~occ
    ragged = free & (rng.random(free.shape) < 0.02)
    grown = np.zeros_like(occ)  # a ragged cell sits next to a wall
    grown[1:, :] |= occ[:-1, :]
    grown[:-1, :] |= occ[1:, :]
    grown[:, 1:] |= occ[:, :-1]
    grown[:, :-1] |= occ[:, 1:]
    occ |= ragged & grown
    classes = np.zeros((height, width), np.uint8)
    for k, (r0, c0, r1, c1) in enumerate(rooms):
        classes[r0:r1, c0:c1] = 2 + k
    classes[occ] = 1
    classes[~known] = 0
    p = np.where(occ, 0.95, 0.05).astype(np.float32)
    p[~known] = 0.5
    for _ in range(int(rng.integers(0, 20))):  # unobserved floor
        r, c = (int(v) for v in rng.integers(0, (height - 20, width - 20)))
        hh, ww = (int(v) for v in rng.integers(5, 20, size=2))
        patch = p[r:r + hh, c:c + ww]
        patch[~occ[r:r + hh, c:c + ww]] = 0.5
    p += rng.normal(0.0, float(rng.uniform(0.02, 0.08)), p.shape).astype(np.float32)
    names = (*ROOM_CLASSES, *(f"room{k + 1}" for k in range(len(rooms))))
    return Scene.build(f"rooms{seed}", ["occupancy"], p[None], classes, names)
