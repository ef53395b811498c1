"""Every limit and its default, in one place; the service config exposes each one.

A limit bounds the work or memory that one message, query or client can cause.  The defaults
are generous for a fleet's real traffic and stop what is absurd (a typo'd resolution, a
hostile payload).  :class:`sogm_service.service.config.LimitSettings` takes its defaults from
here, so every limit can be changed in the config file.
"""

from __future__ import annotations

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

FUSE_WORKERS: Final = 2
"""Threads that fuse ISMs, each over its own share of the tiles (results are the same for any
number); more than the machine's cores buys nothing."""

LAYER_NAME_PATTERN: Final = r"^[A-Za-z0-9_\-./]{1,128}$"
"""What a layer name may be: up to 128 characters of ``[A-Za-z0-9_-./]``."""

MAP_NAME_PATTERN: Final = r"^[A-Za-z0-9_\-]+$"
"""What a map name may be (it is one chunk of every key and of every tile file name)."""

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
