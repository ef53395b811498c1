"""With a tile store, memory stays bounded even when the disk cannot keep up: the writer's queue
is bounded in bytes, dirty tiles stay resident rather than pile up behind it, and while the
map is over its budget new tiles are refused (``memory_budget``)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.admission import Admission
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.stats import Stats
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.writer import TileWriter
from sogm_service.wire.errors import IsmRejectedError
from sogm_service.wire.messages import IsmMessage, PoseModel

T = 32  # 32 x 32 cells, 2 KiB per layer and tile
RES = 0.1


def test_the_writer_counts_the_bytes_it_holds(tmp_path: Path) -> None:
    gate = threading.Event()
    store = DirectoryStore(tmp_path, "m", RES, T)
    original = store.write
    store.write = lambda *a, **kw: (gate.wait(10.0), original(*a, **kw))[1]  # type: ignore
    writer = TileWriter(store)
    try:
        data = [np.zeros((2, T, T), np.int16) for _ in range(3)]
        for k, d in enumerate(data):
            writer.submit(k, 0, ["a", "b"], d, 1.0)
        assert writer.pending_bytes() == 3 * data[0].nbytes  # queued or being written
        writer.submit(1, 0, ["a", "b"], np.zeros((2, T, T), np.int16), 2.0)  # coalesced
        assert writer.pending_bytes() == 3 * data[0].nbytes
        gate.set()
        assert writer.flush(10.0)
        assert writer.pending_bytes() == 0
    finally:
        gate.set()
        writer.close(10.0)
        store.close()


def _config(tmp_path: Path) -> ServiceConfig:
    return ServiceConfig.model_validate({
        "map": {"resolution": RES, "tile_size": T},
        "storage": {"directory": str(tmp_path / "tiles"), "memory_budget_mb": 0.02},
        "limits": {"max_writer_queue_mb": 0.004},  # two snapshots of one 2 KiB layer
    })


def _ism(x: float) -> IsmMessage:
    """A 1 m ISM well inside one tile (its footprint touches no neighbour)."""
    cells = np.full((10, 10), 230, np.uint8)
    return IsmMessage(resolution=RES, origin=PoseModel(x=x + 0.5, y=0.5), width=10,
                      height=10, encoding="prob_u8", data=cells.tobytes())


@pytest.fixture
def stack(tmp_path: Path) -> Any:
    config = _config(tmp_path)
    stats = Stats()
    keeper = Checkpointer(config, stats, keep=set)
    tiled = TiledMap("default", "map", TileLattice(RES, T), loader=keeper.load)
    keeper.attach(tiled)
    assert keeper.store is not None
    gate = threading.Event()
    original = keeper.store.write
    keeper.store.write = lambda *a, **kw: (gate.wait(20.0), original(*a, **kw))[1]  # type: ignore
    admission = Admission(config, stats)
    admission.store_backlog = keeper.writer_full
    try:
        yield config, stats, keeper, tiled, gate, admission
    finally:
        gate.set()
        keeper.close(10.0)


def test_a_saturated_writer_defers_eviction_and_refuses_new_tiles(stack: Any) -> None:
    config, stats, keeper, tiled, gate, admission = stack
    span = T * RES
    for k in range(12):  # 12 tiles of one layer: 24 KiB resident, the budget is 20 KB
        inc = logodds.increments(np.full((T, T), 230, np.uint8), "prob_u8")
        tiled.fuse("obstacle", inc, GridGeometry(RES, T, T, Pose2D(k * span, 0.0, 0.0)))
    assert keeper.checkpoint() == 12  # all dirty; the writer is stuck at its first write
    assert keeper.writer_full()
    resident = tiled.resident_bytes()
    keeper.enforce_budget()  # dirty tiles cannot go: their copies would pile up
    assert tiled.resident_bytes() == resident > config.storage.memory_budget_mb * 1e6
    assert stats.snapshot()[0].get("evictions_deferred_writer_full", 0) > 0
    with pytest.raises(IsmRejectedError) as refused:  # a new tile while over budget
        admission.check_ism(_ism(100 * span), "obstacle", None, tiled)
    assert refused.value.code == "memory_budget" and "saturated" in refused.value.message
    admission.check_ism(_ism(0.0), "obstacle", None, tiled)  # an existing tile: accepted
    gate.set()  # the disk catches up: everything written, eviction proceeds
    assert keeper.writer is not None and keeper.writer.flush(20.0)
    assert not keeper.writer_full()
    keeper.enforce_budget()
    assert tiled.resident_bytes() <= config.storage.memory_budget_mb * 1e6
    admission.check_ism(_ism(100 * span), "obstacle", None, tiled)  # accepted again


def test_admitted_isms_still_queued_reserve_their_tiles(tmp_path: Path) -> None:
    """Without a store, each ISM admitted into new tiles reserves their bytes until it is
    fused: a burst queued behind the fuse workers cannot pass the budget together although
    each one alone would fit."""
    config = ServiceConfig.model_validate({
        "map": {"resolution": RES, "tile_size": T},
        "storage": {"memory_budget_mb": 3 * T * T * 2 / 1e6}})  # room for three planes
    admission = Admission(config, Stats())
    tiled = TiledMap("m", "map", TileLattice(RES, T))
    span = T * RES
    held = [admission.check_ism(_ism(k * 10 * span), "obstacle", None, tiled) for k in range(3)]
    assert held == [T * T * 2] * 3 and admission.reserved_bytes == 3 * T * T * 2
    with pytest.raises(IsmRejectedError) as refused:  # a fourth new tile, nothing fused yet
        admission.check_ism(_ism(40 * span), "obstacle", None, tiled)
    assert refused.value.code == "memory_budget" and "reserved" in refused.value.message
    admission.release(held[0])  # one is fused elsewhere (here: dropped): room again
    assert admission.check_ism(_ism(40 * span), "obstacle", None, tiled) == T * T * 2
