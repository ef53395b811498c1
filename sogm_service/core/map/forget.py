"""Layers that forget: decay toward unknown with a half-life, applied lazily.

The authors' original server had a "forget" (``l *= factor``, :func:`logodds.forget`) run over
the whole map.  Here a layer may have a **half-life** ``h`` (seconds): evidence older by ``dt``
counts ``0.5 ** (dt / h)`` as much, so a moving person's old positions fade to unknown while
walls (layers without a half-life) stay.  Nothing sweeps the map: each tile keeps, per decaying
layer, the time up to which its cells are decayed (``Tile.decay``), and the elapsed time since
then is applied as one multiplication when the tile is touched (:func:`before_write` and
:func:`for_read`, called by :class:`sogm_service.core.map.tiles.TiledMap`):

* **write** (an ISM of stamp ``t`` fused into the tile): if ``t - t_d >= h / 32`` the tile's
  layer is decayed in place by ``0.5 ** ((t - t_d) / h)`` and ``t_d = t``; then the ISM is
  added.  Closer writes add without decaying (``t_d`` stays), so a tile written at 4 Hz is
  multiplied at most every ``h / 32``: the cost is bounded and rounding cannot stall the decay.
  Evidence added in such a window is decayed from ``t_d``, i.e. up to ``2 ** (-1/32)`` (2.1 %)
  more than exactly.  An ISM older than ``t_d`` by ``h / 32`` or more (another robot's, late)
  is added decayed by ``0.5 ** ((t_d - t) / h)``: evidence counts by its age, whatever order
  it arrives in.  A layer's first write into a tile starts its ``t_d`` at that ISM's stamp
  (not at the tile's latest stamp of any layer), so robots writing their own layers give the
  same bits in any interleaving -- on one server and on every cluster member, which may
  receive two robots' ISMs in different orders.
* **read** (a sub-map, a mosaic, scan matching) at time ``now``: the copy is decayed by
  ``0.5 ** ((now - t_d) / h)``; the tile itself is left as it is.  So reads never change the
  map: its state is a function of the ISMs each tile received, in their order, whatever the
  queries did in between (a query between two ISMs cannot change what the second one adds to).

Time is never the wall clock inside the core: writes use the ISM's stamp, reads a ``now``
passed in, by default the map's clock (the latest stamp fused or loaded,
:meth:`TiledMap.now`), so the results are exact functions of the stamps.

**Rounding** (int16 fixed point, 1/1000 nat): ``decayed(l) = trunc(l * f)`` with ``f`` and the
product in float64, truncated toward zero: every decay moves a cell toward unknown (never past
it) and a cell reaches exactly 0 (unknown) in finitely many steps; a read gives what a write at
the same time would leave before adding.

Which layers forget: :class:`ForgetRules`, ``{pattern: half-life}`` matched against layer names
(``fnmatch``; an exact name first, then patterns in the order given).
"""

from __future__ import annotations

import fnmatch
import math
import threading
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from sogm_service.core.map.tile import Tile

QUANTUM = 1.0 / 32.0
"""A tile's layer is decayed in place on write at most every ``QUANTUM * half_life``."""

Fixed = npt.NDArray[np.int16]


def decay_factor(dt: float, half_life: float) -> float:
    """``0.5 ** (dt / half_life)``; 1.0 for ``dt <= 0`` (no decay backwards in time)."""
    if not (half_life > 0 and math.isfinite(half_life)):
        raise ValueError(f"half-life must be positive and finite, got {half_life!r}")
    if not dt > 0:
        return 1.0
    return float(0.5 ** (dt / half_life))


def decayed(state: npt.NDArray[np.int16], factor: float) -> Fixed:
    """A new array: ``trunc(state * factor)`` in float64 (module docstring: rounding)."""
    if not 0.0 <= factor <= 1.0:
        raise ValueError(f"decay factor must lie in [0, 1], got {factor!r}")
    return np.trunc(state.astype(np.float64) * factor).astype(np.int16)


def decayed_into(state: npt.NDArray[np.int16], factor: float, out: npt.NDArray[np.int16],
                 work: npt.NDArray[np.float64]) -> Fixed:
    """:func:`decayed` into ``out`` through ``work`` (float64), both of ``state``'s shape:
    the same bits, no allocation (``out`` may be ``state``)."""
    if not 0.0 <= factor <= 1.0:
        raise ValueError(f"decay factor must lie in [0, 1], got {factor!r}")
    np.multiply(state, factor, out=work)
    np.trunc(work, out=work)
    np.copyto(out, work, casting="unsafe")
    return out


def decay_in_place(state: npt.NDArray[np.int16], factor: float,
                   work: npt.NDArray[np.float64] | None = None) -> None:
    """:func:`decayed`, written back into ``state`` (a no-op for ``factor == 1``); with
    ``work`` (float64, ``state``'s shape) it allocates nothing."""
    if factor == 1.0:
        return
    if work is None:
        np.copyto(state, decayed(state, factor))
    else:
        decayed_into(state, factor, state, work)


class DecayWork(threading.local):
    """Per thread: the memory a decaying layer's write needs in a fuse's phase 2 (the float64
    work array of a decay, a late ISM's aged patch), taken in phase 1 so that phase 2
    allocates nothing.  One tile's worth of each, kept for the next ISM."""

    def __init__(self) -> None:
        self.work: npt.NDArray[np.float64] = np.empty((0, 0), np.float64)
        self.patch: Fixed = np.empty((0, 0), np.int16)

    def ensure(self, tile_size: int) -> DecayWork:
        if self.work.shape != (tile_size, tile_size):
            self.work = np.empty((tile_size, tile_size), np.float64)
            self.patch = np.empty((tile_size, tile_size), np.int16)
        return self


decay_work = DecayWork()


# -- a tile's decaying layer (module docstring: write, read) --------------------------------
def before_write(tile: Tile, lid: int, half_life: float, stamp: float, first: bool,
                 work: DecayWork | None = None) -> float:
    """Before an ISM of ``stamp`` is added to layer ``lid`` of ``tile`` (the caller holds
    ``tile.lock``): the layer decayed up to ``stamp``; returns the factor the ISM's own
    increments take (1.0 unless it is older than the layer's cells: another robot's, late).
    A layer's first write into the tile (``first``) starts its decay stamp at ``stamp``:
    what other layers were written before does not matter, so the result does not depend on
    how ISMs of different robots interleave."""
    if first:
        tile.decay[lid] = stamp
        return 1.0
    t_d = tile.decay.setdefault(lid, tile.stamp)  # a tile from before decay stamps
    if stamp - t_d >= QUANTUM * half_life:
        plane = tile.planes.get(lid)
        if plane is not None:  # an absent plane is unknown: nothing to decay
            decay_in_place(plane, decay_factor(stamp - t_d, half_life),
                           None if work is None else work.work)
        tile.decay[lid] = stamp
    elif t_d - stamp >= QUANTUM * half_life:
        return decay_factor(t_d - stamp, half_life)
    return 1.0


def aged(patch: Fixed, age: float, work: DecayWork | None = None) -> Fixed:
    """A late ISM's patch as old as it is (:func:`before_write`'s factor; into ``work``'s
    memory when given)."""
    if work is None:
        return decayed(patch, age)
    h, w = patch.shape
    return decayed_into(patch, age, work.patch[:h, :w], work.work[:h, :w])


def for_read(tile: Tile, lid: int, half_life: float, block: Fixed, now: float) -> None:
    """A block copied out of layer ``lid`` of ``tile``, as it is at ``now`` (``tile.lock``
    held)."""
    f = decay_factor(now - tile.decay.get(lid, tile.stamp), half_life)
    if f != 1.0:
        block[...] = decayed(block, f)


class ForgetRules:
    """Which layer forgets with which half-life: ``{exact name or fnmatch pattern: seconds}``."""

    def __init__(self, rules: Mapping[str, float] | None = None) -> None:
        self.rules: dict[str, float] = {}
        for pattern, half_life in (rules or {}).items():
            if not pattern:
                raise ValueError("an empty layer pattern")
            decay_factor(1.0, float(half_life))  # validates
            self.rules[pattern] = float(half_life)

    def __bool__(self) -> bool:
        return bool(self.rules)

    def half_life(self, layer: str) -> float | None:
        """The layer's half-life in seconds, or None when it never forgets."""
        if layer in self.rules:
            return self.rules[layer]
        for pattern, half_life in self.rules.items():
            if fnmatch.fnmatchcase(layer, pattern):
                return half_life
        return None
