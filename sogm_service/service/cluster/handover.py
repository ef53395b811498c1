"""The pure parts of a cluster's handover: identities of tile contents, and which
journaled ISMs a pulled tile still needs (:mod:`sogm_service.service.cluster.cluster`)."""

from __future__ import annotations

import hashlib

import numpy as np
import numpy.typing as npt

from sogm_service.core.map.tiletypes import Mark
from sogm_service.service.server.fusers import FuseJob


def content_digest(names: list[str], data: npt.NDArray[np.int16]) -> str:
    """A digest of a tile's content, independent of its layer order and of all-zero layers
    (members learn layers in different orders)."""
    h = hashlib.blake2b(digest_size=16)
    for name, k in sorted((n, k) for k, n in enumerate(names)):
        if k < data.shape[0] and data[k].any():
            h.update(name.encode() + b"\0")
            h.update(np.ascontiguousarray(data[k], dtype="<i2").tobytes())
    return h.hexdigest()


def replay_plan(journal: list[FuseJob], applied: dict[str, Mark]
                ) -> tuple[list[FuseJob], dict[str, Mark]]:
    """Which journaled ISMs a pulled tile still needs, in journal order, and the marks of ISMs
    it holds that this member has not received yet (to skip when they arrive).

    Per ISM key: after the copy's last ISM when the journal has it; all when the copy has none
    of that key or its last is older than the journal's first; none when the copy's last is
    newer than every journaled one (it reached the owner before it reached us)."""
    start: dict[str, int] = {}
    skip: dict[str, Mark] = {}
    by_key: dict[str, list[int]] = {}
    for pos, job in enumerate(journal):
        by_key.setdefault(job.key, []).append(pos)
    for key, positions in by_key.items():
        mark = applied.get(key)
        if mark is None:
            start[key] = 0
            continue
        found = [p for p in positions if (journal[p].stamp, journal[p].digest) == mark]
        if found:
            start[key] = found[-1] + 1
        elif mark[0] < journal[positions[0]].stamp:
            start[key] = 0
        else:
            start[key] = len(journal)
            skip[key] = mark
    for key, mark in applied.items():
        if key not in by_key:
            skip.setdefault(key, mark)  # harmless if it never comes: a newer ISM clears it
    keep = [job for pos, job in enumerate(journal) if pos >= start[job.key]]
    return keep, skip
