"""A cluster member's ingestion of an ISM whose tiles it does not own: the header and the cells'
framing are checked and the robot followed; a zstd frame's decompression, the values inside it
and the increments are the owners'."""

from __future__ import annotations

import numpy as np

from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.pipeline import IngestPipeline, IsmItem
from sogm_service.service.server.server import MapServer
from sogm_service.wire import codec
from sogm_service.wire import compression as zstd
from sogm_service.wire.messages import IsmMessage, PoseModel


def _pipeline(owns: bool) -> IngestPipeline:
    server = MapServer(ServiceConfig())  # not started: no session, the pipeline alone
    server.pipeline.owns_none = lambda box: not owns
    return server.pipeline


def _payload(msg: IsmMessage, **fields: object) -> bytes:
    return codec.encode(msg.model_copy(update=fields))


def _ism() -> IsmMessage:
    cells = np.full((20, 20), 200, np.uint8)
    return IsmMessage(resolution=0.05, origin=PoseModel(x=1.0, y=1.0), width=20, height=20,
                      encoding="prob_u8", data=cells.tobytes(), robot="r1", stamp=5.0)


def _counters(p: IngestPipeline) -> dict[str, int]:
    return p.stats.snapshot()[0]


def _rejected(p: IngestPipeline) -> dict[str, int]:
    return dict(p.stats.rejected)


def test_a_member_that_owns_none_of_the_tiles_leaves_the_decompression_to_the_owners() -> None:
    ism = _ism()
    cut_short = zstd.compress(ism.data)[:-3]  # declares the right size; its content is short
    payload = _payload(ism, data=cut_short, compression="zstd")
    owner, other = _pipeline(owns=True), _pipeline(owns=False)
    owner.handle(IsmItem(0, "ism/r1/obstacle", payload))
    other.handle(IsmItem(0, "ism/r1/obstacle", payload))
    assert _rejected(owner) == {"bad_compression": 1}
    assert not owner.tiled.known_tiles()
    got = _counters(other)
    assert got.get("cluster_isms_elsewhere") == 1 and not _rejected(other)
    assert other.tiled.now() == 5.0  # its clock follows the ISMs it only checks
    assert not other.tiled.known_tiles()


def test_every_member_refuses_cells_whose_framing_is_wrong() -> None:
    """What the header and a frame's header tell (the length, the declared size, not a zstd
    frame at all) every member refuses alike, so any member's acknowledgement says so."""
    ism = _ism()
    bad = [_payload(ism, data=b"not a zstd frame", compression="zstd"),
           _payload(ism, data=zstd.compress(ism.data + b"\0"), compression="zstd"),
           _payload(ism, data=ism.data[:-1])]
    for owns in (True, False):
        p = _pipeline(owns)
        for payload in bad:
            p.handle(IsmItem(0, "ism/r1/obstacle", payload))
        assert _rejected(p) == {"bad_compression": 1, "data_length": 2}, owns
        assert "cluster_isms_elsewhere" not in _counters(p)


def test_a_member_that_owns_none_still_refuses_a_bad_header() -> None:
    other = _pipeline(owns=False)
    other.handle(IsmItem(0, "ism/r1/obstacle", _payload(_ism(), frame="odom")))
    other.handle(IsmItem(0, "ism/r1/obstacle", _payload(_ism(), robot="r2")))
    got = _counters(other)
    assert _rejected(other) == {"wrong_frame": 1, "robot_mismatch": 1}
    assert "cluster_isms_elsewhere" not in got


def test_an_owner_fuses_what_it_owns() -> None:
    owner = _pipeline(owns=True)
    owner.handle(IsmItem(0, "ism/r1/obstacle", codec.encode(_ism().compressed())))
    owner.fusers.drain(5.0)
    assert owner.tiled.known_tiles() and "cluster_isms_elsewhere" not in _counters(owner)
