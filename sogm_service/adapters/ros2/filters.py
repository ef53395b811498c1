"""nav2's costmap filter masks derived from the semantic layers (pure, no zenoh).

nav2's costmap filters (``nav2_costmap_2d::KeepoutFilter`` and ``SpeedFilter``) read a mask, a
``nav_msgs/msg/OccupancyGrid``, and a ``nav2_msgs/msg/CostmapFilterInfo`` that names the mask's
topic and how a cell's value maps to the filter's space (``base + multiplier * value``).  Here
the masks come from the map's layers, named by layer or class pattern
(:mod:`sogm_service.core.classes`: a pattern's matching layers fused by the Bayesian rule):

* **keepout** (filter type 0, base 0, multiplier 1): ``100`` where the most occupied keepout
  class is at or above ``keepout_threshold``; ``0`` where some keepout class has evidence in the
  cell but none reaches the threshold; ``-1`` where no keepout class has any evidence (log-odds
  exactly 0: never observed, or forgotten).  nav2's KeepoutFilter skips ``-1`` (the costmap cell
  stays as it is) and writes a mask value only where it is above the costmap's cost or the
  costmap cell is unknown, so ``0`` never lowers a known cost.
* **speed** (filter type 1, percent of the maximum speed, base 0, multiplier 1: a cell's value
  is its limit): the lowest limit of the speed classes at or above ``speed_threshold`` in the
  cell, ``0`` elsewhere.  nav2's SpeedFilter reads ``0`` as no limit and ``-1`` as an invalid
  cell (it logs an error and keeps the last limit), so the speed mask never holds ``-1``.

A layer that forgets (``[map] forget``) fades: its evidence decays toward 0 as the map's clock
moves on, so its keepout drops to 0 once below the threshold and to -1 once gone.

The rules need numpy only (the viewer draws them without the ``ros2`` extra); the grids
(:func:`mask_grid`, :func:`filter_masks`) need rosbags.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.classes import LayerClass, fuse_classes, member_layers, resolve
from sogm_service.core.geometry import GridGeometry

if TYPE_CHECKING:  # the grids need rosbags (the ros2 extra); the masks' rules do not
    from sogm_service.adapters.ros2.cdr import OccupancyGridFields
    from sogm_service.core.map.tiles import TiledMap

KEEP_OUT = 100
FREE = 0
UNKNOWN = -1
NO_LIMIT = 0

KEEPOUT = "keepout"
SPEED = "speed"
FILTER_TYPES: dict[str, int] = {KEEPOUT: 0, SPEED: 1}
"""CostmapFilterInfo ``type`` of each mask: 0 keepout, 1 speed limit in percent."""
FILTER_BASE = 0.0
FILTER_MULTIPLIER = 1.0


@dataclass(frozen=True)
class FilterSpec:
    """What the masks are made of (the server fills it from ``[nav2]``)."""

    keepout: tuple[str, ...] = ()
    keepout_threshold: float = 0.6
    speed: Mapping[str, int] = field(default_factory=dict)
    speed_threshold: float = 0.6

    @property
    def enabled(self) -> bool:
        return bool(self.keepout or self.speed)

    def masks(self) -> list[str]:
        """The masks this spec makes, in publication order."""
        return [name for name, on in ((KEEPOUT, self.keepout), (SPEED, self.speed)) if on]


def parse_speed(text: str | None) -> dict[str, int]:
    """``PATTERN=PERCENT,...`` (the command line's ``--speed``) -> ``{pattern: percent}``;
    ``ValueError`` for an entry without a pattern or a percent in 1..100."""
    out: dict[str, int] = {}
    for item in (text.split(",") if text else []):
        pattern, sep, pct = item.rpartition("=")
        if not sep or not pattern or not pct.strip().isdigit() or not 1 <= int(pct) <= 100:
            raise ValueError(f"--speed {item!r}: PATTERN=PERCENT with a percent in 1..100")
        out[pattern] = int(pct)
    return out


def spec_from_options(keepout: str | None, keepout_threshold: float, speed: str | None,
                      speed_threshold: float) -> FilterSpec:
    """The masks the command-line options ask (``--keepout A,B``, ``--speed P=N,...`` and
    their thresholds, each a probability in (0.5, 1)); ``ValueError`` for a malformed one."""
    for p in (keepout_threshold, speed_threshold):
        fixed_threshold(p)
    return FilterSpec(keepout=tuple(keepout.split(",")) if keepout else (),
                      keepout_threshold=keepout_threshold, speed=parse_speed(speed),
                      speed_threshold=speed_threshold)


def fixed_threshold(p: float) -> int:
    """The least fixed log-odds (1/1000 nat) whose probability is at least ``p``."""
    if not 0.5 < p < 1.0:
        raise ValueError(f"threshold {p} is not in (0.5, 1)")
    return math.ceil(float(logodds.logit(p)) * logodds.SCALE - 1e-9)


def keepout_cells(planes: npt.NDArray[np.int16], threshold: float) -> npt.NDArray[np.int8]:
    """``(H, W)`` keepout mask of ``(K, H, W)`` class planes (fixed log-odds): 100 kept out,
    0 observed and not kept out, -1 where no plane has evidence (or ``K`` is 0)."""
    if planes.ndim != 3:
        raise ValueError(f"planes of shape {planes.shape}: (K, H, W) expected")
    out = np.full(planes.shape[1:], UNKNOWN, np.int8)
    if planes.shape[0] == 0:
        return out
    observed = np.any(planes != 0, axis=0)
    out[observed] = FREE
    out[np.max(planes, axis=0) >= fixed_threshold(threshold)] = KEEP_OUT
    return out


def speed_cells(planes: npt.NDArray[np.int16], limits: Sequence[int],
                threshold: float) -> npt.NDArray[np.int8]:
    """``(H, W)`` speed mask of ``(K, H, W)`` class planes, plane ``k`` limiting to
    ``limits[k]`` percent where it is at or above ``threshold``: the lowest limit wins where
    several do, 0 (no limit) elsewhere."""
    if planes.ndim != 3 or planes.shape[0] != len(limits):
        raise ValueError(f"planes of shape {planes.shape} for {len(limits)} limits")
    for limit in limits:
        if not 1 <= limit <= 100:
            raise ValueError(f"speed limit {limit} is not a percent in 1..100")
    best = np.full(planes.shape[1:], 101, np.int16)
    thr = fixed_threshold(threshold)
    for plane, limit in zip(planes, limits, strict=True):
        best[(plane >= thr) & (best > limit)] = limit
    best[best == 101] = NO_LIMIT
    return best.astype(np.int8)


@dataclass(frozen=True)
class FilterClasses:
    """The classes each mask reads over the map's current layers (entries matching no layer
    yet are left out: their mask is as if nothing were there)."""

    keepout: list[LayerClass]
    speed: list[LayerClass]
    limits: list[int]

    @property
    def layers(self) -> list[str]:
        return member_layers([*self.keepout, *self.speed])


def filter_classes(spec: FilterSpec, names: Sequence[str]) -> FilterClasses:
    keep = [c for c in resolve(list(spec.keepout), names, allow_empty=True) if c.members]
    entries = list(spec.speed)
    speed = resolve(entries, names, allow_empty=True)
    kept = [(c, spec.speed[e]) for c, e in zip(speed, entries, strict=True) if c.members]
    return FilterClasses(keep, [c for c, _ in kept], [lim for _, lim in kept])


def mask_cells(spec: FilterSpec, stack: npt.NDArray[np.int16], names: Sequence[str],
               classes: FilterClasses) -> dict[str, npt.NDArray[np.int8]]:
    """Each mask of ``spec`` from ``stack`` (``(len(names), H, W)`` fixed log-odds, plane
    ``k`` the layer ``names[k]``)."""
    out: dict[str, npt.NDArray[np.int8]] = {}
    if spec.keepout:
        out[KEEPOUT] = keepout_cells(fuse_classes(stack, names, classes.keepout),
                                     spec.keepout_threshold)
    if spec.speed:
        out[SPEED] = speed_cells(fuse_classes(stack, names, classes.speed), classes.limits,
                                 spec.speed_threshold)
    return out


def mask_grid(cells: npt.NDArray[np.int8], window: GridGeometry, *, frame: str,
              stamp: float) -> OccupancyGridFields:
    """A mask's cells over ``window`` as an OccupancyGrid (the map's extent and origin)."""
    from sogm_service.adapters.ros2.cdr import OccupancyGridFields
    from sogm_service.adapters.ros2.convert import yaw_quaternion

    if cells.shape != window.shape:
        raise ValueError(f"cells of shape {cells.shape}, window {window.shape}")
    o = window.origin
    return OccupancyGridFields(
        frame=frame, stamp=stamp, resolution=window.resolution, width=window.width,
        height=window.height, position=(o.x, o.y, 0.0), orientation=yaw_quaternion(o.yaw),
        data=np.ascontiguousarray(cells, np.int8))


def filter_masks(tiled: TiledMap, window: GridGeometry, spec: FilterSpec, *,
                 frame: str | None = None, stamp: float = 0.0) -> dict[str, OccupancyGridFields]:
    """The masks of ``spec`` over ``window`` (nearest: the window is on the lattice), each
    layer they read sampled once; empty when ``spec`` makes none."""
    if not spec.enabled:
        return {}
    classes = filter_classes(spec, list(tiled.layers))
    read = classes.layers
    if read:
        stack = tiled.sample(window, read, "nearest")
    else:
        stack = np.zeros((0, *window.shape), np.int16)
    frame = frame or tiled.frame
    return {name: mask_grid(cells, window, frame=frame, stamp=stamp)
            for name, cells in mask_cells(spec, stack, read, classes).items()}
