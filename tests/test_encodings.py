"""An exact "no information" in 8-bit and float ISMs (schema version 2; issue 19).

``prob_u8`` keeps its meaning (p = v / 255, no exact unknown); ``prob_u8_v2`` is 0..254 ->
p = v / 254 (127 exactly 0.5) and 255 = unknown; ``prob_f32`` takes NaN as unknown.  Expected
increments are computed here from the definitions (``math.log``), not from the project's LUTs.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from sogm_service.adapters.laser import encode_prob_u8_v2
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.wire import codec
from sogm_service.wire.codec import DecodeError
from sogm_service.wire.messages import IsmMessage
from tests.conftest import ServerProcess, wait_processed

EPS0 = logodds.DEFAULT_EPS0
LO, HI = logodds.clamp_limits(EPS0)


def fixed(p: float) -> int:
    """round(1000 * logit(clip(p, eps0, 1 - eps0))), from the definition."""
    q = min(max(p, EPS0), 1.0 - EPS0)
    return round(1000.0 * math.log(q / (1.0 - q)))


def test_prob_u8_v2_table_from_its_definition() -> None:
    lut = logodds.increment_lut("prob_u8_v2")
    want = [fixed(v / 254.0) for v in range(255)] + [0]
    assert lut.tolist() == want
    assert lut[127] == 0 and lut[255] == 0  # exactly no information, twice
    assert (lut[0], lut[254]) == (LO, HI)  # the clamp ends, as prob_u8's 0 and 255
    assert lut[128] == fixed(128 / 254) == 16  # one step above unknown: log(128 / 126)
    # symmetric about 127: v and 254 - v are opposite evidence
    assert (lut[:127] == -lut[254:127:-1]).all()


def test_prob_u8_keeps_its_meaning_for_robots_already_deployed() -> None:
    lut = logodds.increment_lut("prob_u8")
    assert lut.tolist() == [fixed(v / 255.0) for v in range(256)]
    assert (lut[0], lut[127], lut[128], lut[255]) == (LO, -8, 8, HI)


def _filled_map() -> TiledMap:
    """A map with content (a real ISM in two layers) to watch for any change."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    rng = np.random.default_rng(3)
    p = rng.random((90, 110)).astype(np.float32)
    geom = GridGeometry(0.05, 110, 90, Pose2D(-1.0, -0.7, 0.3))
    for layer in ("a", "b"):
        tiled.fuse(layer, logodds.increments(p, "prob_f32"), geom, "biodds")
    return tiled


def _snapshot(tiled: TiledMap) -> dict[tuple[int, int], bytes]:
    return {k: tiled.tile_layers(t)[1].tobytes() for k, t in tiled.tiles.items()}


UNKNOWN_ISMS = {
    "prob_u8_v2 255": (np.full((40, 50), 255, np.uint8), "prob_u8_v2"),
    "prob_u8_v2 127": (np.full((40, 50), 127, np.uint8), "prob_u8_v2"),
    "prob_u8_v2 mixed": (np.where(np.indices((40, 50)).sum(axis=0) % 2 == 0, 127, 255)
                         .astype(np.uint8), "prob_u8_v2"),
    "prob_f32 NaN": (np.full((40, 50), np.nan, np.float32), "prob_f32"),
    "occupancy_i8 -1": (np.full((40, 50), -1, np.int8), "occupancy_i8"),
}


@pytest.mark.parametrize("name", list(UNKNOWN_ISMS))
def test_all_unknown_isms_leave_the_map_bit_identical_after_10000_fusions(name: str) -> None:
    data, encoding = UNKNOWN_ISMS[name]
    tiled = _filled_map()
    before = _snapshot(tiled)
    inc = logodds.increments(data, encoding)
    assert not inc.any()
    aligned = GridGeometry(0.05, 50, 40, Pose2D(-0.5, -0.5, 0.0))
    rotated = GridGeometry(0.07, 50, 40, Pose2D(0.3, -0.2, 0.8))  # warped with biodds
    far = GridGeometry(0.05, 50, 40, Pose2D(40.0, 40.0, 0.0))  # no tile there yet
    for i in range(10_000):
        tiled.fuse("a", inc, (aligned, rotated)[i % 2], "biodds")
    for interp in ("bilinear", "nearest"):
        tiled.fuse("b", inc, rotated, interp)
    tiled.fuse("a", inc, far, "biodds")
    assert _snapshot(tiled) == before  # same tiles, same bytes


def test_prob_u8_128_as_unknown_drives_the_map_to_the_clamp() -> None:
    """Why prob_u8_v2 exists: a prob_u8 ISM that uses 128 for unknown is +8 units a time."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    geom = GridGeometry(0.05, 8, 8, Pose2D(0.0, 0.0, 0.0))
    inc = logodds.increments(np.full((8, 8), 128, np.uint8), "prob_u8")
    for _ in range(10_000):
        tiled.fuse("a", inc, geom, "biodds")
    assert (tiled.tiles[(0, 0)].planes[0][:8, :8] == HI).all()


def _ism_payload(data: np.ndarray, encoding: str, res: float = 0.05) -> bytes:
    """An ISM packed from the schema's fields (schemas/ism.json), not the project's model."""
    return msgpack.packb({"resolution": res, "origin": {"x": 0.0, "y": 0.0, "yaw": 0.0},
                          "width": int(data.shape[1]), "height": int(data.shape[0]),
                          "encoding": encoding, "data": np.ascontiguousarray(data).tobytes()})


def test_wire_accepts_every_prob_u8_v2_code_and_nan_but_not_infinity() -> None:
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    msg = codec.decode(IsmMessage, _ism_payload(codes, "prob_u8_v2"))
    assert msg.array().tolist() == codes.tolist()
    cells = np.array([[0.2, np.nan], [1.0, 0.0]], np.float32)
    assert np.isnan(codec.decode(IsmMessage, _ism_payload(cells, "prob_f32")).array()).sum() == 1
    for bad, code in (([np.inf, 0.5], "non_finite"), ([np.nan, 1.5], "out_of_range"),
                      ([np.nan, -0.1], "out_of_range")):
        with pytest.raises(DecodeError) as info:
            codec.decode(IsmMessage, _ism_payload(np.array([bad], np.float32), "prob_f32"))
        assert info.value.code == code


def test_prob_f32_nan_cells_are_untouched_and_the_rest_fused() -> None:
    p = np.array([[np.nan, 0.9], [0.1, np.nan]], np.float32)
    inc = logodds.increments(p, "prob_f32")
    assert inc.tolist() == [[0, fixed(float(np.float32(0.9)))], [fixed(float(np.float32(0.1))), 0]]


def test_prob_u8_v2_as_a_reply_encoding() -> None:
    l = np.array([0, LO, HI, 1, -1, 2000], np.int16)
    enc = logodds.encode_fixed(l, "prob_u8_v2")
    assert enc.dtype == np.uint8
    p2000 = 1.0 / (1.0 + math.exp(-2.0))
    assert enc.tolist() == [255, 0, 254, 127, 127, round(p2000 * 254)]
    dec = logodds.decode_to_prob(enc, "prob_u8_v2")
    assert dec[0] == 0.5 and dec[3] == 0.5 and dec[2] == 1.0
    # Every code round-trips through the map (127, p = 0.5, is written as 255: unknown).
    codes = np.arange(256, dtype=np.uint8)
    back = logodds.encode_fixed(logodds.prob_to_fixed(logodds.decode_to_prob(codes,
                                                                             "prob_u8_v2")),
                                "prob_u8_v2")
    want = codes.copy()
    want[127] = 255
    np.testing.assert_array_equal(back, want)


def test_laser_encoder_writes_unknown_as_255() -> None:
    assert encode_prob_u8_v2(np.array([0.0, 0.5, 1.0, np.nan, 0.25])).tolist() == \
        [0, 255, 254, 255, round(0.25 * 254)]


@pytest.mark.integration
def test_prob_u8_v2_over_the_wire(server: ServerProcess) -> None:
    """Codes 0 / 127 / 254 / 255 in four bands, published as raw msgpack to a real server."""
    data = np.zeros((40, 40), np.uint8)
    data[:, 10:20], data[:, 20:30], data[:, 30:] = 127, 254, 255
    nan_ism = np.full((40, 40), np.nan, np.float32)
    with server.client() as client:
        client.publish_raw("ism/r/laser/obstacle", _ism_payload(data, "prob_u8_v2"))
        client.publish_raw("ism/r/laser/obstacle", _ism_payload(nan_ism, "prob_f32"))
        counters = wait_processed(client, 2)
        assert counters.get("isms_fused") == 2, counters
        window = dict(x=1.0, y=1.0, width=2.0, height=2.0, resolution=0.05, interp="nearest")
        l = client.submap(**window, encoding="logodds_i16").data[0]
        v2 = client.submap(**window, encoding="prob_u8_v2").data[0]
    assert (l[:, :10] == LO).all() and (l[:, 10:20] == 0).all()
    assert (l[:, 20:30] == HI).all() and (l[:, 30:] == 0).all()
    assert (v2[:, :10] == 0).all() and (v2[:, 10:20] == 255).all()
    assert (v2[:, 20:30] == 254).all() and (v2[:, 30:] == 255).all()
