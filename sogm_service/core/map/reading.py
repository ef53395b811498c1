"""Reading the tiled map: a window resampled from it (:meth:`Reading.sample`), the map-cell box
it is built from (:meth:`Reading.mosaic`), and the coarse path that reads only the cells a warp
interpolates from (:meth:`Reading.gather`, :meth:`Reading.read_cells`;
:mod:`sogm_service.core.map.gather`).  Decaying layers read as they are at the time asked for.

Pure (numpy only, no I/O).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry, Pose2D, wrap_angle
from sogm_service.core.map import gather
from sogm_service.core.map.footprint import gather_taps, prefer_gather
from sogm_service.core.map.mapstate import MapState
from sogm_service.core.map.tile import Tile
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.core.resample import Interp, dst_to_src, resample_stack

_ALIGN_TOL = 1e-6


class Reading(MapState):
    """The reads of a tiled map, each tile copied under its own lock."""

    def mosaic(self, box: tuple[int, int, int, int], layer_ids: list[int],
               now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layer_ids), h, w)`` log-odds of the map-cell box ``(c0, r0, w, h)``;
        decaying layers as they are at ``now`` (default: :meth:`now`)."""
        c0, r0, w, h = box
        now = self.now() if now is None else now
        t = self.tile_size
        out = np.zeros((len(layer_ids), h, w), dtype=np.int16)
        for j in range(r0 // t, (r0 + h - 1) // t + 1):
            for i in range(c0 // t, (c0 + w - 1) // t + 1):
                tile = self.get_tile((i, j))  # loads an evicted tile back; a read is a use
                if tile is not None:
                    self._copy_block(tile, (i, j), box, layer_ids, out, now)
        return out

    def _copy_block(self, tile: Tile, index: TileIndex, box: tuple[int, int, int, int],
                    layer_ids: list[int], out: npt.NDArray[np.int16],
                    now: float = -math.inf) -> None:
        c0, r0, w, h = box
        t = self.tile_size
        tc, tr = index[0] * t, index[1] * t
        a0, a1 = max(c0, tc), min(c0 + w, tc + t)
        b0, b1 = max(r0, tr), min(r0 + h, tr + t)
        with tile.lock:  # an evicted tile still holds its last state: a consistent read
            for k, lid in enumerate(layer_ids):
                plane = tile.planes.get(lid)
                if plane is not None:  # else unknown: out is zeros already
                    out[k, b0 - r0:b1 - r0, a0 - c0:a1 - c0] = \
                        plane[b0 - tr:b1 - tr, a0 - tc:a1 - tc]
                    self._decay_for_read(tile, lid, out[k, b0 - r0:b1 - r0, a0 - c0:a1 - c0],
                                         now)

    def sample(self, window: GridGeometry, layers: list[str],
               interp: Interp = "biodds", now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layers), H, W)`` fixed log-odds of the map resampled into ``window``.

        Unknown area (no tile, or outside every ISM so far) is 0.  Raises ``KeyError`` for a
        layer the map does not have.
        """
        ids = [self.layer_id(n) for n in layers]
        res = self.lattice.resolution
        xmin, ymin, xmax, ymax = window.bounds()
        # One cell of margin each side so that bilinear reads real neighbours at the edge.
        c0, r0 = math.floor(xmin / res) - 1, math.floor(ymin / res) - 1
        c1, r1 = math.ceil(xmax / res) + 1, math.ceil(ymax / res) + 1
        box = (c0, r0, c1 - c0, r1 - r0)
        if prefer_gather(gather_taps(interp) * window.width * window.height, box[2] * box[3]):
            return self.gather(window, ids, box, interp, now)  # coarse: read only the taps
        src = self.mosaic(box, ids, now)
        src_geom = GridGeometry(res, box[2], box[3], Pose2D(c0 * res, r0 * res, 0.0))
        if _is_aligned(src_geom, window):
            du, dv = _cell_offset(src_geom, window)
            return np.ascontiguousarray(src[:, dv:dv + window.height, du:du + window.width])
        return resample_stack(src, src_geom, window, interp)

    # -- the gather path of coarse windows (:mod:`sogm_service.core.map.gather`) ----------------
    def gather(self, window: GridGeometry, layer_ids: list[int], box: tuple[int, int, int, int],
               interp: Interp = "biodds", now: float | None = None) -> npt.NDArray[np.int16]:
        """What :meth:`sample` returns for ``window`` (map-cell ``box`` its full path would
        build), reading only the cells the warp would interpolate from (1 or 4 per output
        cell) instead of the whole box."""
        c0, r0, bw, bh = box
        res = self.lattice.resolution
        src_geom = GridGeometry(res, bw, bh, Pose2D(c0 * res, r0 * res, 0.0))
        taps = gather.taps(dst_to_src(src_geom, window)[:2], bw, bh, window.width,
                           window.height, interp)
        values = np.zeros((len(layer_ids), *taps.u.shape), dtype=np.int16)
        values[:, taps.inside] = self.read_cells(taps.u[taps.inside] + c0,
                                                 taps.v[taps.inside] + r0, layer_ids, now)
        return gather.combine(values, taps, interp)

    def read_cells(self, u: npt.NDArray[np.int64], v: npt.NDArray[np.int64],
                   layer_ids: list[int], now: float | None = None) -> npt.NDArray[np.int16]:
        """``(len(layer_ids), n)`` log-odds of the map cells ``(u[k], v[k])`` (0 where there
        is no tile), decaying layers as at ``now``: :meth:`mosaic` for scattered cells, tile
        by tile under each tile's lock."""
        now = self.now() if now is None else now
        t = self.tile_size
        out = np.zeros((len(layer_ids), u.size), dtype=np.int16)
        if u.size == 0:
            return out
        ti, tj = u // t, v // t
        order = np.lexsort((ti, tj))
        ti_s, tj_s = ti[order], tj[order]
        starts = np.flatnonzero(np.r_[True, (ti_s[1:] != ti_s[:-1]) | (tj_s[1:] != tj_s[:-1])])
        ends = np.r_[starts[1:], order.size]
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            index = (int(ti_s[a]), int(tj_s[a]))
            tile = self.get_tile(index)  # loads an evicted tile back; a read is a use
            if tile is None:
                continue
            sel = order[a:b]
            lu, lv = u[sel] - index[0] * t, v[sel] - index[1] * t
            with tile.lock:  # as _copy_block: an evicted tile still holds its last state
                for k, lid in enumerate(layer_ids):
                    plane = tile.planes.get(lid)
                    if plane is not None:  # else unknown: out is zeros already
                        cells = plane[lv, lu]  # a copy (fancy indexing)
                        self._decay_for_read(tile, lid, cells, now)
                        out[k, sel] = cells
        return out


def _is_aligned(src: GridGeometry, dst: GridGeometry) -> bool:
    """Same resolution and heading, and ``dst`` starts on a cell corner of ``src``."""
    if abs(src.resolution - dst.resolution) > _ALIGN_TOL * src.resolution:
        return False
    if abs(wrap_angle(dst.origin.yaw - src.origin.yaw)) > 1e-9:
        return False
    m = src.world_to_cell() @ dst.cell_to_world()
    return bool(np.all(np.abs(m[:2, 2] - np.rint(m[:2, 2])) < _ALIGN_TOL))


def _cell_offset(src: GridGeometry, dst: GridGeometry) -> tuple[int, int]:
    m = src.world_to_cell() @ dst.cell_to_world()
    return int(np.rint(m[0, 2])), int(np.rint(m[1, 2]))
