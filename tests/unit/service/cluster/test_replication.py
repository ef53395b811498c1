"""What replicas and cluster members send each other (service/cluster/replication): tile files
with their stamp, decay stamps and marks."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.config import ServiceConfig
from sogm_service.wire.errors import TileFormatError


def test_a_sent_tile_carries_stamp_decay_and_marks_and_a_wrong_one_is_refused() -> None:
    """What replicas and cluster members send each other (``TileFiles``): the receiver gets
    the sender's stamp, decay stamps and marks; a tile answered for another index, or
    damaged, is refused and changes nothing."""
    from sogm_service.service.cluster.replication import TileFiles

    config = ServiceConfig.model_validate({"map": {"resolution": 0.1, "tile_size": 32,
                                                   "forget": {"people": 5.0}}})
    files = TileFiles.of(config.map)
    sender = TiledMap("default", "map", TileLattice(0.1, 32))
    sender.set_forget({"people": 5.0})
    inc = np.full((4, 4), 700, np.int16)
    sender.fuse("people", inc, GridGeometry(0.1, 4, 4, Pose2D(0.0, 0.0, 0.0)), stamp=10.0,
                mark=("ism/r1/people", (10.0, 7)))
    sender.fuse("people", inc, GridGeometry(0.1, 4, 4, Pose2D(0.0, 0.0, 0.0)), stamp=12.0,
                mark=("ism/r1/people", (12.0, 8)))
    snap = sender.snapshot((0, 0))
    assert snap is not None and snap.decay
    blob = files.encode(snap)

    receiver = TiledMap("default", "map", TileLattice(0.1, 32))
    with pytest.raises(TileFormatError):
        files.install(receiver, blob, (1, 0))  # answered for another tile
    with pytest.raises(TileFormatError):
        files.install(receiver, blob[:-10], (0, 0))  # damaged
    assert receiver.known_tiles() == set()
    files.install(receiver, blob, (0, 0))
    got = receiver.snapshot((0, 0))
    assert got is not None
    assert (got.stamp, got.decay, got.applied) == (snap.stamp, snap.decay, snap.applied)
    assert got.layers == snap.layers and np.array_equal(got.data, snap.data)
