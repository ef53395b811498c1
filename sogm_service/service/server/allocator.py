"""Process-wide tuning of glibc's allocator for the long-running server processes.

Why: every ISM and every query makes temporaries of 128 KiB to a few MiB (lookup-table
output, float warp buffers, reply arrays).  glibc serves blocks that large with a fresh
``mmap`` and gives them back with ``munmap`` when freed, so each one is page-faulted again on
first touch.  In a virtual machine a fault costs 1-2 us per 4 KiB page: measured here, building
a 4 x 256 x 256 sub-map reply (sampling, encoding, msgpack) took 2.8-3.6 ms with fresh mappings
and 0.9 ms with reused heap memory, the same code in the same process.  Keeping such blocks on
the heap (a fixed mmap threshold) and not trimming the heap top after every free makes them
reused.

The cost: freed memory up to ``trim_threshold`` stays with the process instead of going back
to the OS (at most 64 MiB at the heap top); peak RSS (``VmHWM``) hardly moves (the memory
bench: 194 -> 200 MB).  A tile's planes (128 KiB each) then live on the heap too, between
other live blocks, so the planes of evicted tiles are free memory that no automatic trim
returns (a server with a 64 MB budget stayed at 555 MB RSS after a burst, its heap full of
holes).  :func:`give_back` (``malloc_trim(0)``, which releases the free pages inside every
arena, not only at its top) returns them: the checkpoint thread calls it once evicted tiles
are written (:meth:`~sogm_service.service.server.checkpoints.Checkpointer.give_back_memory`),
and the same server went down to 174-203 MB.  It runs without the GIL and takes 0.5-30 ms (the
more free pages, the longer).

Only the entry points of long-running processes call this (``serve``, ``demo``, ``replay``,
``bench``), never an import: a library must not change its host's allocator.  An explicit
``MALLOC_MMAP_THRESHOLD_`` in the environment wins (glibc's own tunable).  Elsewhere than glibc
(musl, macOS) it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys

# glibc's mallopt parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 1024 * 1024
"""Blocks below 32 MiB (glibc's largest dynamic threshold) come from the heap and are reused."""

TRIM_THRESHOLD = 64 * 1024 * 1024
"""Free memory at the heap top goes back to the OS only beyond 64 MiB (twice the largest
block kept on the heap)."""


def keep_large_allocations(mmap_threshold: int = MMAP_THRESHOLD,
                           trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Serve large temporaries from the reused heap; True when glibc took the settings."""
    if not sys.platform.startswith("linux") or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and \
        bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))


def give_back() -> bool:
    """Return the free pages of every malloc arena to the OS (glibc's ``malloc_trim(0)``):
    True when glibc released some.  Elsewhere than glibc it does nothing."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return bool(trim(0))
