"""Fusing on several workers: bit-identical maps for any number of them; queries never wait
for an ingestion burst; nothing lost."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server.fusers import FuseJob, FuseWorkers

T = 32  # small tiles: every ISM spans several, so the workers share most ISMs


def random_stream(n: int, seed: int) -> list[tuple[str, np.ndarray, GridGeometry]]:
    """ISMs of random size, pose, resolution and layer over a few tiles, overlapping a lot."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        h, w = (int(v) for v in rng.integers(5, 70, size=2))
        res = float(rng.choice([0.05, 0.05, 0.075, 0.1]))
        origin = Pose2D(float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)),
                        float(rng.choice([0.0, rng.uniform(-math.pi, math.pi)])))
        p = rng.uniform(0.0, 1.0, size=(h, w)).astype(np.float32)
        out.append((f"layer{int(rng.integers(0, 3))}",
                    logodds.increments(p, "prob_f32"), GridGeometry(res, w, h, origin)))
    return out


def fuse_all(stream: list[tuple[str, np.ndarray, GridGeometry]], workers: int) -> TiledMap:
    tiled = TiledMap("m", "map", TileLattice(0.05, T))
    fusers = FuseWorkers(tiled, workers)
    done: list[int] = []
    for k, (layer, inc, geometry) in enumerate(stream):
        tiled.layer_id(layer, create=True)  # as the pipeline does: layers in arrival order
        fusers.submit(FuseJob(layer, inc, geometry, "biodds" if k % 3 else "nearest",
                              float(k), done=lambda touched, err: done.append(err is None)))
    assert fusers.drain(60.0)
    fusers.close(10.0)
    assert done == [True] * len(stream)
    return tiled


def tiles_of(tiled: TiledMap) -> dict[tuple[int, int], tuple[list[str], bytes, float]]:
    out = {}
    for tile in tiled.resident():
        names, data = tiled.tile_layers(tile)
        out[tile.index] = (names, data.tobytes(), tile.stamp)
    return out


@pytest.mark.parametrize("workers", [2, 3, 4])
def test_any_number_of_workers_gives_the_one_worker_map_bit_for_bit(workers: int) -> None:
    stream = random_stream(150, seed=workers)
    one = tiles_of(fuse_all(stream, 1))
    many = tiles_of(fuse_all(stream, workers))
    assert len(one) > 20
    assert many.keys() == one.keys()
    for index in one:
        assert many[index] == one[index], index


def test_each_row_of_tiles_belongs_to_one_worker_and_neighbouring_rows_differ() -> None:
    """Rows, not tiles: a rotated ISM is warped a row of tiles at a time, so a row shared by
    two workers would be warped twice."""
    fusers = FuseWorkers(TiledMap("m", "map", TileLattice(0.05, T)), 2)
    try:
        assert fusers.owner((0, 0)) == fusers.owner((1, 0)) == fusers.owner((-5, 0))
        assert fusers.owner((0, 0)) != fusers.owner((0, 1)) != fusers.owner((3, 2))
        assert {fusers.owner((i, j)) for i in range(-3, 3) for j in range(-3, 3)} == {0, 1}
    finally:
        fusers.close(5.0)
