"""The handover's replay plan (service/cluster/handover): a joiner replays exactly the ISMs
of its journal that the copy it pulled does not hold, going by the copy's applied marks (the
last ISM fused into a tile per ISM key, ``Tile.applied``), live or read back from a store.

Its helpers (``mild_ism``, ``numbered_jobs``) also serve the store and cluster tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.cluster.handover import replay_plan
from sogm_service.service.server.fusers import FuseJob
from sogm_service.store.directory import DirectoryStore

RES = 0.1
T = 16


def mild_ism(rng: np.random.Generator, x: int, y: int) -> tuple[np.ndarray, GridGeometry]:
    """Mild, aligned increments (no cell near the clamp: Eq. 1 is exact integer addition)."""
    inc = rng.integers(-40, 41, (12, 20)).astype(np.int16)
    return inc, GridGeometry(RES, 20, 12, Pose2D(x * RES, y * RES, 0.0))


KEYS = ["ism/r1/laser/obstacle", "ism/r2/laser/obstacle"]


def numbered_jobs(n: int) -> list[FuseJob]:
    """ISM number 1..n, alternating publishers, each spanning tiles (0, 0) and (1, 0)."""
    rng = np.random.default_rng(17)
    out = []
    for k in range(1, n + 1):
        inc, geom = mild_ism(rng, int(rng.integers(4, 14)), int(rng.integers(0, 4)))
        key = KEYS[k % 2]
        out.append(FuseJob(key.split("/")[1], inc, geom, "nearest", float(k),
                           lambda touched, error: None, key=key, digest=1000 + k))
    return out


def test_the_replay_plan_with_stored_marks_neither_loses_nor_repeats(tmp_path: Path) -> None:
    """Marks written with a tile and read back give the same plan as the live marks did."""
    jobs = numbered_jobs(6)
    tiled = TiledMap("lab", "map", TileLattice(RES, T))
    for job in jobs[:4]:
        job.fuse(tiled, None)
    live = tiled.tiles[(0, 0)].applied
    with DirectoryStore(tmp_path, "lab", RES, T, frame="map") as store:
        snap = tiled.snapshot((0, 0))
        assert snap is not None
        store.write(0, 0, snap.layers, snap.data, snap.stamp, applied=snap.applied)
        loaded = store.loader(0, 0)
    assert loaded is not None and len(loaded) == 5
    stored = loaded[4]
    assert stored == live
    keep, skip = replay_plan(jobs[1:], stored)
    assert [j.stamp for j in keep] == [5.0, 6.0] and not skip


def _job(key: str, stamp: float, digest: int) -> FuseJob:
    return FuseJob("l", np.zeros((1, 1), np.int16), None, "nearest", stamp,  # type: ignore
                   lambda t, e: None, key=key, digest=digest)


def test_replay_plan_neither_loses_nor_repeats() -> None:
    journal = [_job("a", 1, 11), _job("b", 1, 21), _job("a", 2, 12), _job("b", 2, 22),
               _job("a", 3, 13)]
    # the copy holds a up to stamp 2 and b up to 1: replay a3 and b2, in journal order
    keep, skip = replay_plan(journal, {"a": (2.0, 12), "b": (1.0, 21)})
    assert [(j.key, j.stamp) for j in keep] == [("b", 2), ("a", 3)] and not skip
    # the copy has nothing of a, and b from before the journal started: replay all
    keep, skip = replay_plan(journal, {"b": (0.5, 20)})
    assert len(keep) == 5 and not skip
    # the copy is ahead of us on a (a4 reached its owner first): replay no a, skip until a4
    keep, skip = replay_plan(journal, {"a": (4.0, 14)})
    assert [j.key for j in keep] == ["b", "b"] and skip == {"a": (4.0, 14)}
