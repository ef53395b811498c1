"""Compressed ISMs and replies through a real server: the same map and the same answers as raw,
several times fewer bytes, and a small payload that claims or expands to a huge grid refused
with its code and counted, the map unchanged."""

from __future__ import annotations

import threading

import msgpack
import numpy as np
import pytest
import zenoh
import zstandard

from sogm_service.core.geometry import Pose2D
from sogm_service.wire import codec
from sogm_service.wire.messages import IsmMessage, PoseModel
from tests.conftest import ServerProcess, wait_processed, wait_until
from tests.helpers import raw_session

pytestmark = pytest.mark.integration


def _walls(seed: int) -> np.ndarray:
    """A laser-like ISM: unknown, free and a few walls (what robots send)."""
    rng = np.random.default_rng(seed)
    grid = np.full((256, 256), 128, np.uint8)
    grid[20:230, 20:230] = 20
    for _ in range(6):
        r = int(rng.integers(20, 230))
        grid[r:r + 2, 20:230] = 240
    return grid




def test_compressed_isms_fuse_as_raw_ones_for_a_fraction_of_the_bytes(
        server: ServerProcess) -> None:
    received: dict[str, int] = {"raw": 0, "zstd": 0}
    lock = threading.Lock()

    def count(sample: zenoh.Sample) -> None:
        with lock:
            received["raw" if "/raw/" in str(sample.key_expr) else "zstd"] += len(
                sample.payload.to_bytes())

    watcher = raw_session(server.endpoint)
    try:
        sub = watcher.declare_subscriber("ism/**", count)
        with server.client() as robot:
            for k in range(5):
                grid = _walls(k)
                origin = Pose2D(0.3 * k, 0.2 * k, 0.1 * k)
                robot.compression = None
                robot.publish_ism("ism/robot1/raw/obstacle", grid, resolution=0.05,
                                  origin=origin, wait=True)
                robot.compression = "zstd"
                robot.publish_ism("ism/robot1/zstd/obstacle", grid, resolution=0.05,
                                  origin=origin, wait=True)
            window = dict(x=5.0, y=5.0, width=14.0, height=14.0, encoding="logodds_i16")
            raw = robot.submap(layers=["robot1/raw/obstacle"], **window)
            packed = robot.submap(layers=["robot1/zstd/obstacle"], **window)
            assert np.array_equal(raw.data, packed.data)
            assert np.count_nonzero(raw.data) > 10_000
        assert wait_until(lambda: received["zstd"] > 0 and received["raw"] > 0)
        sub.undeclare()
    finally:
        watcher.close()
    with lock:
        assert received["raw"] > 20 * received["zstd"], received


def test_replies_are_compressed_when_asked_and_decode_to_the_same_reply(
        server: ServerProcess) -> None:
    with server.client() as robot:
        robot.publish_ism("ism/robot1/laser/obstacle", _walls(1), resolution=0.05, wait=True)
        robot.compression = None
        plain = robot.submap(x=6.0, y=6.0, width=12.0, height=12.0, resolution=0.05)
        robot.compression = "zstd"
        packed = robot.submap(x=6.0, y=6.0, width=12.0, height=12.0, resolution=0.05)
        assert np.array_equal(plain.data, packed.data)
        counters = robot.stats().counters
        assert counters.get("replies_zstd", 0) >= 1 and counters.get("replies_raw", 0) >= 1

    raw = raw_session(server.endpoint)
    try:
        selector = "sogm/default/submap?x=6;y=6;width=12;height=12;resolution=0.05"
        (as_is,) = list(raw.get(selector, timeout=10.0))
        (small,) = list(raw.get(selector + ";compression=zstd", timeout=10.0))
        assert as_is.ok is not None and small.ok is not None
        assert str(small.ok.encoding) == "application/msgpack;zstd"
        big, little = as_is.ok.payload.to_bytes(), small.ok.payload.to_bytes()
        expanded = zstandard.ZstdDecompressor().decompress(little)
        assert msgpack.unpackb(expanded)["data"] == msgpack.unpackb(big)["data"]
        assert len(big) > 10 * len(little)
        (refused,) = list(raw.get(selector + ";compression=lz4", timeout=10.0))
        assert refused.err is not None
        assert msgpack.unpackb(refused.err.payload.to_bytes())["code"] == "bad_parameter"
    finally:
        raw.close()


def _hostile(data: bytes, width: int, height: int) -> bytes:
    return codec.encode(IsmMessage.model_construct(
        layer=None, frame="map", stamp=0.0, robot=None, resolution=0.05, origin=PoseModel(),
        width=width, height=height, encoding="prob_u8", data=data, compression="zstd"))


def test_hostile_compressed_isms_are_refused_with_their_code_and_change_nothing(
        server: ServerProcess) -> None:
    bomb = zstandard.ZstdCompressor().compress(bytes(500_000_000))  # 500 MB of zeros
    sizeless = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(100))
    with server.client() as robot:
        robot.publish_raw("ism/robot1/laser/bomb", _hostile(bomb, 10, 10))
        robot.publish_raw("ism/robot1/laser/sizeless", _hostile(sizeless, 10, 10))
        robot.publish_raw("ism/robot1/laser/garbage", _hostile(b"not a zstd frame", 10, 10))
        robot.publish_raw("ism/robot1/laser/huge", _hostile(b"tiny", 1 << 20, 1 << 20))
        stats = wait_processed(robot, 4)
        assert stats.get("isms_fused", 0) == 0
        rejected = robot.stats().rejected
        assert rejected.get("data_length") == 1
        assert rejected.get("bad_compression") == 2
        assert rejected.get("too_large") == 1
        assert robot.info().layers == []
