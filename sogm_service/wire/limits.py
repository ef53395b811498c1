"""Every limit and its default, in one place; the service config exposes each one.

A limit bounds the work or memory that one message, query or client can cause.  The defaults
are generous for a fleet's real traffic and stop what is absurd (a typo'd resolution, a
hostile payload).  :class:`sogm_service.service.config.LimitSettings` takes its defaults from
here, so every limit can be changed in the config file; :data:`LIMITS` says, for each
configurable one, its unit, the refusal code it produces and the stats counter that counts it
(the configuration reference shows that table, generated).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

MAX_PAYLOAD_BYTES: Final = 128 * 1024 * 1024
"""Largest ISM payload accepted, checked before it is queued or decoded."""

MAX_MSGPACK_STR: Final = 1 << 20
"""Longest msgpack string inside any payload (names are short; a huge one is hostile)."""

MAX_ISM_CELLS: Final = 4096 * 4096
"""Largest ISM grid (width x height cells)."""

MAX_ISM_TILES: Final = 1024
"""Most map tiles one ISM's footprint may touch (a wrong resolution would create millions)."""

MAX_QUERY_CELLS: Final = 4096 * 4096
"""Most cells (window cells x layers) one query may ask for."""

QUEUE_SIZE: Final = 64
"""ISMs waiting between the Zenoh callbacks and the ingestion worker."""

FUSE_WORKERS: Final = 1
"""Threads that fuse ISMs, each over its own share of the tiles (the map is the same for any
number).  1 on a 2-core machine: measured there, the server ingests 2300-2500 ISM/s with 1
worker and 1700-1800 with 2 (the GIL-held Python per tile and OpenCV's own threads leave no
core to gain); raise it on machines with cores to spare and measure with ``sogm-service bench
ingest``."""

LAYER_NAME_PATTERN: Final = r"^[A-Za-z0-9_\-./]{1,128}$"
"""What a layer name may be: up to 128 characters of ``[A-Za-z0-9_-./]``."""

MAP_NAME_PATTERN: Final = r"^[A-Za-z0-9_\-]+$"
"""What a map name may be (it is one chunk of every key and of every tile file name)."""

# -- admission: every cost priced from a header before any work -------------------

WORLD_EXTENT_M: Final = 1_000_000.0
"""Half-width (m) of the square world around the map origin: every ISM corner, pose and query
window must lie in ``[-extent, extent]^2`` (``out_of_world``).  Also keeps every tile index
far inside int64 and every coordinate finite."""

MAX_LAYERS: Final = 256
"""Most layers one map may hold; an ISM that would add one more is refused (``too_many_layers``)."""

MAX_ROBOTS: Final = 4096
"""Most robots the fleet tracker follows; a pose or ISM of one more is refused
(``too_many_robots``)."""

MAX_PENDING_POSES: Final = 8192
"""Poses waiting for the pose worker; beyond, the waiting ones are coalesced latest-per-robot
(``poses_coalesced``), so a flood costs O(limit + robots) memory and is never dropped uncounted."""

MAX_ROBOT_NAME: Final = 128
"""Longest robot name (characters) in a key or a message (``name_too_long``)."""

MAX_LAYER_NAME: Final = 128
"""Longest layer name (characters) (``name_too_long``; the pattern also says at most 128)."""

MAX_QUERY_READ_CELLS: Final = 4096 * 4096
"""Most map cells (at map resolution, x layers) one window query may read, whatever the
resolution of its reply (``window_too_large``)."""

MAX_REPLY_BYTES: Final = 64 * 1024 * 1024
"""Largest reply payload a query may cause, priced from its window before sampling
(``reply_too_large``)."""

MAX_SUPERCELL_CELLS: Final = 1024 * 1024
"""Most window cells one ``supercells`` query may segment (SEVDS is the heaviest query)."""

MAX_HEAVY_QUERIES: Final = 2
"""Heavy queries (``supercells``) running at once; one more is answered ``busy``."""

BUSY_RETRY_S: Final = 1.0
"""The retry hint (``retry_after_s``) sent with ``busy``."""

LOG_TEXT_CHARS: Final = 200
"""Rejection log lines cut every attacker-controlled string to this many characters."""

WARMUP_WAIT_S: Final = 2.0
"""How long a supercells query waits for the SEVDS kernels to finish compiling (first start
after an install or upgrade; cached afterwards) before it answers ``warming_up``."""

SUPERCELLS_TIMEOUT_S: Final = 90.0
"""The client's default budget for a supercells query, retries on ``warming_up`` included
(a cold numba compile took 7 s at load 4.4 on 2 cores)."""

ACK_TABLE_SIZE: Final = 16384
"""Outcomes of ISMs that asked for an acknowledgement, kept per server (the oldest go first)."""

ISM_ID_PATTERN: Final = r"^[A-Za-z0-9_.\-]{1,64}$"
"""What an ISM id (the Zenoh attachment of an ISM that asks for an acknowledgement) may be."""

REJECTION_MESSAGE_CHARS: Final = 200
"""A rejection report's message is cut to this many characters."""

MAX_WRITER_QUEUE_MB: Final = 256.0
"""Tile snapshots waiting for the store's disk, at most (MB).  Beyond it dirty tiles are not
evicted (their copies would pile up) and, while the resident tiles are over the memory budget,
ISMs that could add tiles are refused with ``memory_budget``: memory stays within the budget
plus this queue plus a fixed overhead whatever the disk's speed."""

MAX_REGION_TILES: Final = 1024
"""Most tiles one ``tiles/changed`` query's region may span, and most versions it may say it
holds (``window_too_large``)."""

MEMORY_BUDGET_MB: Final = 1024.0
"""Resident tiles, at most (MB): with a store the least recently used are evicted, without one
an ISM that could grow them past it is refused (``memory_budget``)."""


# -- how each configurable limit shows ----------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Limit:
    """A configurable limit as the operator sees it."""

    default: int | float
    """Its default: the constant above (the config field's default is the same constant)."""
    unit: str
    bounds: str
    """What it bounds: the config field's description."""
    refused_as: str = ""
    """The refusal code of what is over it; empty when nothing is refused (coalesced,
    dropped, or a hint)."""
    counters: tuple[str, ...] = ()
    """The stats counters that count what it refused, dropped or deferred."""


LIMITS: Final[dict[str, Limit]] = {
    "limits.max_payload_bytes": Limit(
        MAX_PAYLOAD_BYTES, "bytes", "An ISM payload, checked before it is queued or decoded.",
        "too_large", ("rejected[too_large]",)),
    "limits.max_ism_cells": Limit(
        MAX_ISM_CELLS, "cells", "An ISM grid (width x height cells).",
        "too_large", ("rejected[too_large]",)),
    "limits.max_ism_tiles": Limit(
        MAX_ISM_TILES, "tiles", "Map tiles one ISM's footprint touches, counted arithmetically "
        "from its header (a wrong resolution would create millions; a 1-cell ISM claiming "
        "64 km cells is refused in microseconds).", "too_large", ("rejected[too_large]",)),
    "limits.world_extent_m": Limit(
        WORLD_EXTENT_M, "m", "Half-width of the square world around the map origin: every ISM "
        "corner, pose and query window centre lies in [-extent, extent]^2 (every number finite; "
        "tile indices stay far inside int64).", "out_of_world",
        ("rejected[out_of_world]", "poses_rejected_out_of_world",
         "query_errors_out_of_world")),
    "limits.max_layers": Limit(
        MAX_LAYERS, "layers", "Layers one map may hold; an ISM that would add one more is "
        "refused.", "too_many_layers", ("rejected[too_many_layers]",)),
    "limits.max_robots": Limit(
        MAX_ROBOTS, "robots", "Robots the fleet tracker follows (from poses and from ISMs "
        "naming a robot); a pose or ISM of one more is refused.", "too_many_robots",
        ("rejected[too_many_robots]", "poses_rejected_too_many_robots")),
    "limits.max_robot_name": Limit(
        MAX_ROBOT_NAME, "characters", "Longest robot name in a key or a message.",
        "name_too_long", ("rejected[name_too_long]", "poses_rejected_name_too_long")),
    "limits.max_layer_name": Limit(
        MAX_LAYER_NAME, "characters", "Longest layer name, at most 128 (the layer name pattern, "
        "refused as bad_layer, also allows at most 128).", "name_too_long",
        ("rejected[name_too_long]",)),
    "storage.memory_budget_mb": Limit(
        MEMORY_BUDGET_MB, "MB", "Resident tiles. With a tile store the least recently used "
        "stored tiles are evicted, and ISMs are refused only while the store's writer is "
        "saturated (max_writer_queue_mb). Without one, an ISM that could grow the resident "
        "tiles beyond the budget is refused, priced at one plane per footprint tile that lacks "
        "the layer's plane (an ISM that adds no plane is never refused for memory). ISMs "
        "admitted but still queued for the fuse workers hold a reservation of the tiles they "
        "may add (stats reserved_mb), so a burst cannot pass the budget together.",
        "memory_budget", ("rejected[memory_budget]",)),
    "limits.max_writer_queue_mb": Limit(
        MAX_WRITER_QUEUE_MB, "MB", "Tile snapshots waiting for the store's disk. Beyond it "
        "dirty tiles stay resident and, over the memory budget, ISMs that could add tiles are "
        "refused: memory stays within the budget plus this queue plus a fixed overhead however "
        "slow the disk.", "memory_budget",
        ("rejected[memory_budget]", "evictions_deferred_writer_full")),
    "limits.max_pending_poses": Limit(
        MAX_PENDING_POSES, "poses", "Poses waiting for the pose worker; beyond, the waiting "
        "ones are coalesced latest-per-robot, so a flood costs O(limit + robots) memory and "
        "no pose is dropped uncounted.", "", ("poses_coalesced",)),
    "limits.max_query_cells": Limit(
        MAX_QUERY_CELLS, "cells", "Cells one query returns (window cells x layers).",
        "window_too_large", ("query_errors_window_too_large",)),
    "limits.max_query_read_cells": Limit(
        MAX_QUERY_READ_CELLS, "cells", "Map cells one window query reads (x layers), whatever "
        "the resolution of its reply: 4 x its reply cells (1 x for nearest) when the window is "
        "coarse enough to be gathered, otherwise its box at map resolution; the message names "
        "the cells it would read.", "window_too_large", ("query_errors_window_too_large",)),
    "limits.max_reply_bytes": Limit(
        MAX_REPLY_BYTES, "bytes", "A query's reply payload, priced from its window and "
        "encoding before sampling.", "reply_too_large", ("query_errors_reply_too_large",)),
    "limits.max_supercell_cells": Limit(
        MAX_SUPERCELL_CELLS, "cells", "The window one supercells query segments (SEVDS is the "
        "heaviest query).", "window_too_large", ("query_errors_window_too_large",)),
    "limits.max_region_tiles": Limit(
        MAX_REGION_TILES, "tiles", "Tiles one tiles/changed query's region spans, counted from "
        "its bounds before any tile is read, and versions it may say it holds; every tile "
        "that changed goes back whole, so this also bounds its replies.", "window_too_large",
        ("query_errors_window_too_large",)),
    "limits.max_heavy_queries": Limit(
        MAX_HEAVY_QUERIES, "queries", "Heavy queries (supercells) running at once; one more is "
        "answered busy with a retry hint (busy_retry_s).", "busy",
        ("queries_busy", "query_errors_busy")),
    "limits.busy_retry_s": Limit(
        BUSY_RETRY_S, "s", "The retry hint (retry_after_s) sent with busy."),
    "limits.queue_size": Limit(
        QUEUE_SIZE, "ISMs", "ISMs waiting between the Zenoh callbacks and the ingestion worker; "
        "when it is full, queue_policy says what happens.", "", ("isms_dropped_latest",)),
    "limits.log_text_chars": Limit(
        LOG_TEXT_CHARS, "characters", "Rejection log lines cut every attacker-controlled string "
        "to this length (one line a second per reason)."),
}
"""Every configurable limit by its config path (``section.field``), in the order the
configuration reference lists them."""

