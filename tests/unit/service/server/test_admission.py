"""Admission prices an ISM by the planes it can add: a tile holds one plane per layer written
into it, so a new tile costs one plane, not one per layer of the map; heavy queries beyond
their bound are refused as busy with a retry hint."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.config import LimitSettings, ServiceConfig
from sogm_service.service.server.admission import Admission
from sogm_service.service.server.stats import Stats
from sogm_service.wire.errors import BusyError, IsmRejectedError
from sogm_service.wire.messages import IsmMessage, PoseModel

T = 32  # 2 KiB per plane
RES = 0.1
SPAN = T * RES
PLANE = T * T * 2


def _ism(i: int) -> IsmMessage:
    """A 1 m ISM well inside tile ``(i, 0)`` (its footprint touches no neighbour)."""
    cells = np.full((10, 10), 230, np.uint8)
    return IsmMessage(resolution=RES, origin=PoseModel(x=i * SPAN + 0.5, y=0.5), width=10,
                      height=10, encoding="prob_u8", data=cells.tobytes())


def _fuse(tiled: TiledMap, layer: str, i: int) -> None:
    inc = logodds.increments(np.full((10, 10), 230, np.uint8), "prob_u8")
    tiled.fuse(layer, inc, GridGeometry(RES, 10, 10, Pose2D(i * SPAN + 0.5, 0.5, 0.0)))


@pytest.fixture
def setup() -> tuple[TiledMap, Admission]:
    # No store: nothing can be evicted, so admission prices every ISM; 20 planes fit.
    config = ServiceConfig.model_validate({
        "map": {"resolution": RES, "tile_size": T},
        "storage": {"memory_budget_mb": 20 * PLANE / 1e6},
    })
    tiled = TiledMap("default", "map", TileLattice(RES, T))
    for k in range(18):  # 18 layers, all in tile (0, 0): 18 planes resident
        _fuse(tiled, f"layer{k}", 0)
    assert tiled.resident_bytes() == 18 * PLANE
    return tiled, Admission(config, Stats())


def test_a_new_tile_of_a_many_layer_map_costs_one_plane(setup: tuple[TiledMap, Admission]
                                                        ) -> None:
    tiled, admission = setup
    reserved = admission.check_ism(_ism(5), "layer3", None, tiled)  # 19 planes <= 20
    assert reserved == PLANE
    _fuse(tiled, "layer3", 5)
    admission.release(reserved)  # fused: as the pipeline does
    assert tiled.resident_bytes() == 19 * PLANE  # what admission priced
    reserved = admission.check_ism(_ism(6), "brand_new", None, tiled)  # a new layer, tile: 20
    _fuse(tiled, "brand_new", 6)
    admission.release(reserved)
    assert tiled.resident_bytes() == 20 * PLANE
    with pytest.raises(IsmRejectedError) as refused:  # a 21st plane
        admission.check_ism(_ism(7), "layer3", None, tiled)
    assert refused.value.code == "memory_budget"


def test_isms_that_add_no_plane_are_accepted_over_the_budget(setup: tuple[TiledMap, Admission]
                                                              ) -> None:
    tiled, admission = setup
    _fuse(tiled, "far", 9)  # a layer only tile (9, 0) has
    for k in range(3):  # 22 planes: over the budget
        _fuse(tiled, f"extra{k}", 0)
    assert tiled.resident_bytes() > 20 * PLANE
    admission.check_ism(_ism(0), "layer7", None, tiled)  # tile (0, 0) has layer7's plane
    admission.check_ism(_ism(9), "far", None, tiled)
    for layer in ["far", "another_new_layer"]:  # tile (0, 0) lacks a plane of them
        with pytest.raises(IsmRejectedError) as refused:
            admission.check_ism(_ism(0), layer, None, tiled)
        assert refused.value.code == "memory_budget"


def test_heavy_queries_beyond_the_bound_are_busy_with_a_retry_hint() -> None:
    """The bound itself, in one process: through a server, Zenoh hands one queryable's queries
    to its callback one at a time, so a second heavy query cannot overlap a first there; the
    bound matters once queries run on worker threads."""
    config = ServiceConfig(limits=LimitSettings(max_heavy_queries=2, busy_retry_s=0.5))
    stats = Stats()
    admission = Admission(config, stats)
    with admission.heavy(), admission.heavy():
        with pytest.raises(BusyError) as err, admission.heavy():
            pass
        assert err.value.code == "busy" and err.value.retry_after_s == 0.5
    with admission.heavy():  # slots come back
        pass
    assert stats.snapshot()[0]["queries_busy"] == 1


def _forgetting(half_life: float) -> tuple[TiledMap, Admission]:
    config = ServiceConfig.model_validate({
        "map": {"resolution": RES, "tile_size": T, "forget": {"*/people": half_life}}})
    tiled = TiledMap("default", "map", TileLattice(RES, T))
    tiled.set_forget(config.map.forget)
    return tiled, Admission(config, Stats())


def _stamped(stamp: float) -> IsmMessage:
    return _ism(0).model_copy(update={"stamp": stamp})


def test_an_ism_its_forgetting_layer_would_keep_nothing_of_is_stale() -> None:
    h, now = 10.0, 1.7e9
    tiled, admission = _forgetting(h)
    inc = logodds.increments(np.full((10, 10), 255, np.uint8), "prob_u8")  # at the clamp
    geom = GridGeometry(RES, 10, 10, Pose2D(0.5, 0.5, 0.0))
    tiled.fuse("r1/people", inc, geom, "nearest", stamp=now)
    assert tiled.now() == now
    limit = logodds.weightless_age(h, logodds.clamp_limits(0.001)[1])
    # just within the limit: accepted, and the ISM still leaves evidence where it was put
    admission.check_ism(_stamped(now - limit * 0.999), "r2/people", None, tiled)
    tiled.fuse("r2/people", inc, geom, "nearest", stamp=now - limit * 0.999)
    assert tiled.sample(geom, ["r2/people"], "nearest").max() >= 1
    # just past it: refused from the header; had it been fused, it would hold nothing
    with pytest.raises(IsmRejectedError) as err:
        admission.check_ism(_stamped(now - limit * 1.001), "r3/people", None, tiled)
    assert (err.value.code, err.value.parameter) == ("stale_stamp", "stamp")
    assert "(half-life 10 s)" in str(err.value)
    assert len(str(err.value)) < 200  # whole in the ack and in the log line
    assert "r3/people" not in tiled.layers  # nothing of the map was touched
    tiled.fuse("r4/people", inc, geom, "nearest", stamp=now - limit * 1.001)
    assert not tiled.sample(geom, ["r4/people"], "nearest").any()
    # any stamp further back, however far: one short reason
    with pytest.raises(IsmRejectedError, match="keeps nothing older than") as err:
        admission.check_ism(_stamped(-1e300), "r1/people", None, tiled)
    assert err.value.code == "stale_stamp" and len(str(err.value)) < 200
    # layers that never forget take any stamp, and so does an empty map
    admission.check_ism(_stamped(0.0), "r1/walls", None, tiled)
    empty, fresh = _forgetting(h)
    fresh.check_ism(_stamped(0.0), "r1/people", None, empty)
