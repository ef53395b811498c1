"""Admission: every ISM, pose and query priced from its header before any work.

It is the one place a query's cells and bytes are priced: the query handlers
(:mod:`~sogm_service.service.server.queries`) ask :meth:`Admission.check_query`, then sample.

Each check raises the refusal with its code (:mod:`sogm_service.wire.errors`) and changes
nothing; the caller counts and logs it as every other refusal.  The arithmetic lives in
:mod:`sogm_service.core.map.footprint` (nothing proportional to the footprint is built).

* ISMs: names (``name_too_long``), a stamp its forgetting layer would keep nothing of
  (``stale_stamp``), the world extent (``out_of_world``), the tiles the footprint
  touches (``too_large``), then under the map's lock a new layer (``too_many_layers``), a new
  robot (``too_many_robots``) and, without a tile store, the bytes of the tiles it may create
  (``memory_budget``).
* Poses: name length and world extent (the robot count is the fleet tracker's).
* Queries: every number finite and the centre in the world (``out_of_world``), the cells
  returned and the map cells read at map resolution (``window_too_large``; a coarse window
  is priced at the cells its gather path reads, :mod:`~sogm_service.core.map.gather`), the
  reply bytes
  (``reply_too_large``), and at most ``max_heavy_queries`` supercells at once (``busy``).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from sogm_service.core import logodds
from sogm_service.core.map import footprint as fp
from sogm_service.core.map.forget import ForgetRules
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.stats import Stats
from sogm_service.wire.errors import BusyError, IsmRejectedError, QueryError
from sogm_service.wire.messages import IsmHeader, IsmMessage
from sogm_service.wire.queries import SupercellRequest, TilesChangedRequest, WindowRequest

if TYPE_CHECKING:
    from sogm_service.service.server.fleet import FleetTracker

TileIndex4 = tuple[int, int, int, int]
_BYTES_PER_CELL = {"prob_u8": 1, "prob_u8_v2": 1, "occupancy_i8": 1, "logodds_i16": 2,
                   "prob_f32": 4}
_REPLY_OVERHEAD = 4096  # the reply's fields besides its array
_NODE_BYTES = 96  # a supercell node without its per-layer lists (msgpack, generous)


class Admission:
    """The limits of :class:`~sogm_service.service.config.LimitSettings`, applied."""

    def __init__(self, config: ServiceConfig, stats: Stats) -> None:
        self.config = config
        self.limits = config.limits
        self.stats = stats
        self.resolution = config.map.resolution
        self.tile_size = config.map.tile_size
        self.span = config.map.resolution * config.map.tile_size
        self._has_store = config.storage.directory is not None or config.store.url is not None
        self._budget = int(config.storage.memory_budget_mb * 1e6)
        # With a store: whether its writer is saturated (then nothing more can be evicted and
        # new tiles are priced as without a store).  Set by the pipeline.
        self.store_backlog: Callable[[], bool] | None = None
        self._heavy = threading.BoundedSemaphore(self.limits.max_heavy_queries)
        # Bytes of tiles that admitted ISMs not yet fused may still create (the fuse workers'
        # queues): priced like resident bytes, released when the ISM is fused or fails.
        self._reserved = 0
        self._reserved_lock = threading.Lock()
        self._forget = ForgetRules(config.map.forget)
        self._clamp = logodds.clamp_limits(config.map.eps0)[1]  # the most a cell can hold

    # -- ISMs -----------------------------------------------------------------------------
    def check_names(self, layer: str | None, robot: str | None) -> None:
        lim = self.limits
        if layer is not None and len(layer) > lim.max_layer_name:
            raise IsmRejectedError("name_too_long", f"the layer name has {len(layer)} "
                                   f"characters; the limit is {lim.max_layer_name}", "layer")
        if robot is not None and len(robot) > lim.max_robot_name:
            raise IsmRejectedError("name_too_long", f"the robot name has {len(robot)} "
                                   f"characters; the limit is {lim.max_robot_name}", "robot")

    def check_stamp(self, stamp: float, layer: str, now: float) -> None:
        """Refuse (``stale_stamp``) an ISM of a forgetting layer stamped so long before the
        map's clock ``now`` that, read at that clock, no cell keeps a unit of its evidence
        (:func:`~sogm_service.core.logodds.weightless_age` of the clamp): it would be acked
        as fused and change nothing.  Layers that never forget take any stamp."""
        half_life = self._forget.half_life(layer)
        if half_life is None:
            return
        limit = logodds.weightless_age(half_life, self._clamp)
        if not now - stamp > limit:  # also an empty map (now = -inf)
            return
        raise IsmRejectedError(
            "stale_stamp", f"stamp {stamp:.14g} is {now - stamp:.4g} s before the map's clock "
            f"{now:.14g}; its layer (half-life {half_life:.4g} s) keeps nothing older than "
            f"{limit:.4g} s (stamps: Unix time in s)", "stamp")

    def footprint(self, msg: IsmHeader) -> fp.Footprint:
        """The ISM's footprint from its header: ``out_of_world`` or ``too_large`` refused."""
        o = msg.origin
        bounds = fp.grid_bounds(msg.resolution, msg.width, msg.height, o.x, o.y, o.yaw)
        extent = self.limits.world_extent_m
        if not fp.in_world(bounds, extent):
            raise IsmRejectedError(
                "out_of_world", f"the ISM spans x {bounds[0]:.6g}..{bounds[2]:.6g}, y "
                f"{bounds[1]:.6g}..{bounds[3]:.6g} m; the world is +-{extent:g} m around the "
                "map origin (check its origin and resolution)", "origin")
        foot = fp.bounds_footprint(bounds, self.resolution, self.tile_size)
        if foot.tile_count > self.limits.max_ism_tiles:
            raise IsmRejectedError("too_large", f"the ISM covers {foot.tile_count} tiles "
                                   f"({foot.map_cells} map cells); the limit is "
                                   f"{self.limits.max_ism_tiles} (check its resolution)",
                                   "resolution")
        return foot

    def check_ism(self, msg: IsmMessage, layer: str, robot: str | None, tiled: TiledMap,
                  fleet: FleetTracker | None = None) -> int:
        """Every check of an ISM before it is aligned or fused, from its header and the map's
        counts.  Returns the bytes of tiles reserved for it (see :meth:`release`): the ISMs
        admitted before and still queued for the fuse workers are priced by their
        reservations, so a burst cannot slip past the budget while they wait."""
        self.check_names(layer, robot)
        self.check_stamp(msg.stamp, layer, tiled.now())
        foot = self.footprint(msg)
        if robot and fleet is not None:
            fleet.check_robot(robot)
        new_layer = layer not in tiled.layers
        n_layers = len(tiled.layers)
        if new_layer and n_layers >= self.limits.max_layers:
            raise IsmRejectedError("too_many_layers", f"the map has {n_layers} layers, "
                                   f"the limit; refusing layer {layer[:64]!r}", "layer")
        backlog = self._has_store and self.store_backlog is not None and self.store_backlog()
        if not self._has_store or backlog:
            return self._check_memory(foot, tiled,
                                      None if new_layer else tiled.layer_id(layer),
                                      n_layers + int(new_layer),
                                      "the tile store's writer is saturated "
                                      "(max_writer_queue_mb)" if backlog
                                      else "there is no tile store to evict to")
        return 0

    def release(self, reserved: int) -> None:
        """An admitted ISM is fused (or failed): its reservation is now resident or void."""
        if reserved:
            with self._reserved_lock:
                self._reserved -= reserved

    @property
    def reserved_bytes(self) -> int:
        return self._reserved

    def _check_memory(self, foot: fp.Footprint, tiled: TiledMap, lid: int | None,
                      layers_after: int, why: str) -> int:
        """When nothing can be evicted (no store, or its writer saturated): refuse what could
        grow the tiles past the budget (priced as if every footprint tile were written: an
        upper bound); otherwise reserve that growth until the ISM is fused.  A tile holds a
        plane per layer written into it: writing costs one plane where the tile lacks this
        layer's (``lid``; None: a new layer), a stored tile loaded back at most one per
        layer."""
        resident_bytes = tiled.resident_bytes()
        resident, stored = tiled.tiles, tiled.stored
        plane = self.tile_size * self.tile_size * 2
        i0, j0, i1, j1 = foot.tiles
        grow = 0
        for j in range(j0, j1 + 1):  # at most max_ism_tiles: footprint() checked that
            for i in range(i0, i1 + 1):
                tile = resident.get((i, j))
                if tile is None and (i, j) in stored:
                    grow += layers_after * plane
                elif tile is None or lid is None or lid not in tile.planes:
                    grow += plane
        if not grow:  # existing tiles may always be written
            return 0
        with self._reserved_lock:
            held = resident_bytes + self._reserved
            if held + grow > self._budget:
                raise IsmRejectedError(
                    "memory_budget", f"the ISM may add {grow / 1e6:.1f} MB of tiles to "
                    f"{held / 1e6:.1f} MB resident or reserved by queued ISMs; the budget is "
                    f"{self._budget / 1e6:.1f} MB and {why}",
                    "storage.memory_budget_mb")
            self._reserved += grow
        return grow

    # -- poses ----------------------------------------------------------------------------
    def check_pose(self, robot: str, x: float, y: float) -> None:
        """A pose's robot name and position (the robot count is the fleet's check)."""
        self.check_names(None, robot)
        extent = self.limits.world_extent_m
        if not fp.point_in_world(x, y, extent):
            raise IsmRejectedError("out_of_world", f"pose ({x:.6g}, {y:.6g}) m is outside the "
                                   f"world of +-{extent:g} m", "x")

    # -- queries --------------------------------------------------------------------------
    def check_query(self, req: WindowRequest, n_layers: int,
                    reply_layers: int | None = None) -> fp.WindowPrice:
        """Price a window query before sampling: refused unless every number is sane, the
        centre in the world, the cells returned and read (``n_layers`` sampled) and the reply
        bytes (``reply_layers`` planes, default ``n_layers``: a class replies as one) in their
        limits.
        """
        lim = self.limits
        res = req.resolution or self.resolution
        if not fp.point_in_world(req.x, req.y, lim.world_extent_m):
            raise QueryError("out_of_world", f"the window centre ({req.x:.6g}, {req.y:.6g}) m "
                             f"is outside the world of +-{lim.world_extent_m:g} m", "x")
        price = fp.window_price(req.x, req.y, req.yaw, req.width, req.height, res,
                                self.resolution, req.interp)
        if price is None:
            raise QueryError("window_too_large", f"a window of {req.width:.6g} x "
                             f"{req.height:.6g} m at {res:.6g} m cells has no finite cell "
                             "count", "width")
        n = max(n_layers, 1)
        n_out = n if reply_layers is None else max(reply_layers, 1)
        if price.cells * n > lim.max_query_cells:
            raise QueryError("window_too_large",
                             f"{price.cells} cells x {n_layers} layers exceed the limit of "
                             f"{lim.max_query_cells} cells; ask for a smaller window or a "
                             "coarser resolution", "width")
        if price.read_cells * n > lim.max_query_read_cells:
            raise QueryError("window_too_large",
                             f"the window reads {price.read_cells} map cells (at "
                             f"{self.resolution:g} m) x {n_layers} layers, more than the limit "
                             f"of {lim.max_query_read_cells}; ask for a smaller window or a "
                             "much coarser resolution (a window at least 4 x 4 map cells per "
                             "reply cell reads only the cells it interpolates)",
                             "width")
        if isinstance(req, SupercellRequest):
            if price.cells > lim.max_supercell_cells:
                raise QueryError("window_too_large",
                                 f"supercells of {price.cells} cells exceed the limit of "
                                 f"{lim.max_supercell_cells}", "width")
            reply = self._supercell_bytes(price, n_out, req.labels, req.block_size)
        else:
            per = _BYTES_PER_CELL.get(req.encoding, 4)
            layers_out = 1 if hasattr(req, "method") else n_out
            reply = price.cells * layers_out * per + _REPLY_OVERHEAD
        if reply > lim.max_reply_bytes:
            raise QueryError("reply_too_large", f"the reply would take about {reply} bytes; "
                             f"the limit is {lim.max_reply_bytes}", "width")
        return price

    def check_region(self, req: TilesChangedRequest, held: int) -> TileIndex4:
        """A ``tiles/changed`` region as inclusive tile bounds ``(i0, j0, i1, j1)``, from its
        numbers alone: a box or index bounds (``bad_parameter`` for neither, both or an empty
        one), its centre in the world (``out_of_world``), at most ``max_region_tiles`` tiles
        and versions held (``window_too_large``)."""
        lim = self.limits.max_region_tiles
        bounds = (req.i0, req.j0, req.i1, req.j1)
        if any(b is not None for b in bounds) or req.width is None or req.height is None:
            if req.width is not None or req.height is not None or None in bounds:
                raise QueryError("bad_parameter", "name the region by width and height (and "
                                 "x, y) or by all of i0, j0, i1, j1", "width")
            i0, j0, i1, j1 = (int(b or 0) for b in bounds)
            if i1 < i0 or j1 < j0:
                raise QueryError("bad_parameter", "tile bounds need i0 <= i1 and j0 <= j1", "i1")
        else:
            if not fp.point_in_world(req.x, req.y, self.limits.world_extent_m):
                raise QueryError("out_of_world", f"the region centre ({req.x:.6g}, "
                                 f"{req.y:.6g}) m is outside the world", "x")
            s, w2, h2 = self.span, req.width / 2, req.height / 2
            if max(w2, h2) > lim * s:
                raise QueryError("window_too_large", f"a region of {req.width:.6g} x "
                                 f"{req.height:.6g} m spans more than {lim} tiles", "width")
            i0, j0 = math.floor((req.x - w2) / s), math.floor((req.y - h2) / s)
            i1 = max(i0, math.ceil((req.x + w2) / s) - 1)
            j1 = max(j0, math.ceil((req.y + h2) / s) - 1)
        count = (i1 - i0 + 1) * (j1 - j0 + 1)
        if count > lim or held > lim:
            raise QueryError("window_too_large", f"the region spans {count} tiles and holds "
                             f"{held} versions; the limit is {lim} of each", "width")
        return i0, j0, i1, j1

    @staticmethod
    def _supercell_bytes(price: fp.WindowPrice, n_layers: int, labels: bool,
                         block_size: int) -> int:
        """An upper bound of a supercells reply: at most one node per block (SEVDS starts
        from blocks and only merges), each with two floats per layer and its neighbours."""
        nodes = max(1, (price.width // block_size) * (price.height // block_size))
        per_node = _NODE_BYTES + 18 * n_layers + 9 * 8
        return _REPLY_OVERHEAD + nodes * per_node + (price.cells * 4 if labels else 0)

    @contextmanager
    def heavy(self, what: str = "supercells") -> Iterator[None]:
        """Hold one of the ``max_heavy_queries`` slots, or refuse with ``busy`` at once."""
        if not self._heavy.acquire(blocking=False):
            retry = self.limits.busy_retry_s
            self.stats.count("queries_busy")
            raise BusyError(f"{self.limits.max_heavy_queries} {what} queries are running; "
                            f"retry after {retry:g} s", retry)
        try:
            yield
        finally:
            self._heavy.release()

    # -- reporting ------------------------------------------------------------------------
    def reportable_tiles(self, known: Iterable[TileIndex]) -> list[TileIndex]:
        """The known tiles ``info`` may list: those in the world (nothing stored outside it
        can break a reply; admission keeps new ones out in the first place)."""
        extent = self.limits.world_extent_m
        return sorted(t for t in known if fp.tile_in_world(t[0], t[1], self.span, extent))

    def bounds_of(self, tiles: list[TileIndex]) -> tuple[float, float, float, float] | None:
        """The metric box of ``tiles`` (as ``TiledMap.bounds`` computes it, from the
        reportable tiles only)."""
        if not tiles:
            return None
        ii = [i for i, _ in tiles]
        jj = [j for _, j in tiles]
        s = self.span
        return (min(ii) * s, min(jj) * s, (max(ii) + 1) * s, (max(jj) + 1) * s)
