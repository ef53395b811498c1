"""Tile file format (store/format): round trip, the readable header, every corruption refused
with a reason, files of older layouts."""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geodesy import GeoPoint
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tilemanager import TileManager
from sogm_service.core.map.tiletypes import Mark
from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.tilefile import (
    MAGIC,
    MAX_APPLIED,
    MAX_APPLIED_KEY,
    Expectation,
    tile_file_name,
    tile_from_bytes,
    tile_header,
    tile_to_bytes,
)
from tests.unit.store.test_directory import LAYERS, RES, T, header, open_store, stack


def test_file_name_tags_kind_resolution_size_and_location() -> None:
    assert tile_file_name("lab", 0.05, 256, 3, -12) == "sogm_lab_r0.050_t256_i+0003_j-0012.tile"
    assert tile_file_name("m", 0.0125, 64, -1, 0) == "sogm_m_r0.0125_t64_i-0001_j+0000.tile"


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    data = stack(1)
    with open_store(tmp_path, datum=GeoPoint(48.0, 11.0, 500.0)) as store:
        info = store.write(3, -12, LAYERS, data, 123.25)
        assert info.path.name == "sogm_lab_r0.050_t32_i+0003_j-0012.tile"
    with open_store(tmp_path) as again:
        index = again.index()
        assert list(index) == [(3, -12)]
        tile = again.load(3, -12)
    assert tile is not None
    assert np.array_equal(tile.data, data) and tile.data.dtype == np.int16
    assert tile.data.flags.writeable  # the map fuses into it in place
    h = tile.header
    assert (h.map_name, h.frame, h.index, h.resolution, h.tile_size) == ("lab", "map", (3, -12),
                                                                          RES, T)
    assert h.layers == tuple(LAYERS) and h.stamp == 123.25 and h.scale == logodds.SCALE
    assert h.origin == pytest.approx((3 * RES * T, -12 * RES * T))
    assert h.datum is not None and h.datum.latitude < 48.0 < h.datum.latitude + 0.01
    manager = TileManager(TileLattice(RES, T), 0.5, 1, datum=GeoPoint(48.0, 11.0, 500.0))
    assert h.datum == manager.tile_datum(3, -12)  # events and files agree on the datum
    assert index[(3, -12)].header == h
    layers, arr, stamp = again.loader(3, -12)  # type: ignore[misc]
    assert layers == LAYERS and stamp == 123.25 and np.array_equal(arr, data)


def test_header_is_readable_json_after_a_fixed_prefix(tmp_path: Path) -> None:
    blob = tile_to_bytes(header(), stack(2))
    magic, version, _, hlen = struct.unpack_from("<8sHHI", blob)
    assert magic == MAGIC and version == 1
    fields = json.loads(blob[16:16 + hlen])
    assert fields["shape"] == [2, T, T] and fields["dtype"] == "<i2"
    assert fields["layers"] == LAYERS and fields["i"] == 3 and fields["j"] == -12
    payload = blob[16 + hlen + 4:]
    assert fields["payload_crc32"] == zlib.crc32(payload)
    assert np.array_equal(np.frombuffer(zlib.decompress(payload), "<i2").reshape(2, T, T),
                          stack(2))


def test_wire_bytes_are_the_file_bytes_and_a_replica_stores_them(tmp_path: Path) -> None:
    data = stack(3)
    with open_store(tmp_path / "a") as primary:
        primary.write(0, 0, LAYERS, data, 5.0)
        blob = primary.read_bytes(0, 0)
        assert blob == primary.path_for(0, 0).read_bytes()
    assert blob is not None
    with open_store(tmp_path / "b") as replica:
        info = replica.write_bytes(blob)
        assert info.path.read_bytes() == blob
        loaded = replica.load(0, 0)
        assert loaded is not None and np.array_equal(loaded.data, data)
        with pytest.raises(TileFormatError, match="map 'other'"):
            replica.write_bytes(tile_to_bytes(header(map_name="other"), data))
        assert replica.index() == {(0, 0): replica.indexed()[(0, 0)]}


def test_full_size_tile_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    data = np.zeros((8, 256, 256), dtype=np.int16)
    data[:, :, :150] = rng.integers(-6907, 6908, (8, 256, 150))
    with DirectoryStore(tmp_path, "lab", RES, 256) as store:
        info = store.write(-1, 2, [f"c{k}" for k in range(8)], data, 1.0)
        assert info.size < data.nbytes
        tile = store.load(-1, 2)
    assert tile is not None and np.array_equal(tile.data, data)


def test_encoder_refuses_inconsistent_stacks() -> None:
    with pytest.raises(ValueError, match="shape"):
        tile_to_bytes(header(layers=["a"]), stack(5))
    with pytest.raises(ValueError, match="int16"):
        tile_to_bytes(header(), stack(5).astype(np.int32))
    with pytest.raises(ValueError, match="unique"):
        tile_to_bytes(header(layers=["a", "a"]), stack(5))


def test_every_truncation_and_bit_flip_is_rejected_with_a_reason() -> None:
    blob = tile_to_bytes(header(), stack(6))
    rng = np.random.default_rng(6)
    cuts = sorted({*range(0, 40), *rng.integers(40, len(blob), 60).tolist()})
    for cut in cuts:
        with pytest.raises(TileFormatError) as err:
            tile_from_bytes(blob[:cut])
        assert err.value.reason
    for pos in [*range(0, 24), *rng.integers(24, len(blob), 150).tolist()]:
        flipped = bytearray(blob)
        flipped[pos] ^= 1 << int(rng.integers(8))
        with pytest.raises(TileFormatError):
            tile_from_bytes(bytes(flipped))
    with pytest.raises(TileFormatError, match="trailing"):
        tile_from_bytes(blob + b"\0")
    assert np.array_equal(tile_from_bytes(blob).data, stack(6))


def test_specific_reasons() -> None:
    good = tile_to_bytes(header(), stack(7))
    with pytest.raises(TileFormatError, match="magic"):
        tile_from_bytes(b"PK\x03\x04" + good[4:])
    with pytest.raises(TileFormatError, match="version"):
        tile_from_bytes(good[:8] + b"\x02\x00" + good[10:])
    with pytest.raises(TileFormatError, match="header checksum"):
        tile_from_bytes(good.replace(b'"lab"', b'"lax"'))
    with pytest.raises(TileFormatError, match="payload checksum"):
        tile_from_bytes(good[:-3] + bytes(b ^ 0xFF for b in good[-3:]))


def test_values_outside_the_fixed_point_range_are_rejected() -> None:
    bad = stack(8)
    bad[0, 0, 0] = logodds.MAX_STATE + 1  # would break the no-overflow guarantee of fusion
    with pytest.raises(TileFormatError, match="outside"):
        tile_from_bytes(tile_to_bytes(header(), bad))


GOLDEN = (Path(__file__).resolve().parents[2] / "data"
          / "sogm_golden_r0.050_t16_i+0003_j-0002.tile")


def test_a_tile_file_written_before_the_package_layout_loads_and_reencodes_byte_for_byte(
        tmp_path: Path) -> None:
    """``tests/data`` holds a tile file written by an earlier build of the package: its bytes
    load and re-encode identically, so the format is what files on disk already hold."""
    blob = GOLDEN.read_bytes()
    tile = tile_from_bytes(blob)
    h = tile.header
    assert (h.map_name, h.frame, h.index, h.resolution, h.tile_size) == \
        ("golden", "map", (3, -2), 0.05, 16)
    assert h.layers == ("robot1/laser/obstacle", "floor", "pallet")
    assert h.stamp == 1234.5 and h.written_unix == 1764400000.0
    assert h.datum is not None and (h.datum.latitude, h.datum.longitude) == (48.1, 11.5)
    expected = np.load(GOLDEN.with_name("golden_tile_layers.npy"))
    np.testing.assert_array_equal(tile.data, expected)
    assert tile_to_bytes(h, tile.data) == blob  # same header + data -> the very same bytes
    shutil.copy(GOLDEN, tmp_path / GOLDEN.name)
    with DirectoryStore(tmp_path, "golden", 0.05, 16) as store:
        assert list(store.index()) == [(3, -2)]
        loaded = store.load(3, -2)
        assert loaded is not None
        np.testing.assert_array_equal(loaded.data, expected)


# -- applied marks: the last ISM fused into a tile per ISM key, in the header's ``applied``
# field.  Malformed fields are forged from the file layout in ``store/format.py``'s docstring
# (prefix, JSON header, CRC-32, payload), not with the project's encoder.
MARK_RES, MARK_T = 0.1, 16
EXPECT = Expectation("lab", MARK_RES, MARK_T, "map")


MARKS: dict[str, Mark] = {"sogm/lab/ism/r1/laser/obstacle": (12.5, 2**64 - 1),
                          "sogm/lab/ism/r2/laser/obstacle": (7.0, 0),
                          "sogm/lab/ism/r3/cam/people": (1700000000.25, 123456789)}


def _stack(seed: int, n: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(-3000, 3000, (n, MARK_T, MARK_T)).astype(np.int16)


def _json_header(blob: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON header and the payload of a tile, read by the documented layout."""
    magic, version, _, hlen = struct.unpack_from("<8sHHI", blob)
    assert magic == b"SOGMTILE" and version == 1
    (crc,) = struct.unpack_from("<I", blob, 16 + hlen)
    assert zlib.crc32(blob[:16 + hlen]) == crc
    return json.loads(blob[16:16 + hlen]), blob[20 + hlen:]


def _forge(fields: dict[str, Any], payload: bytes) -> bytes:
    """A tile file with this JSON header (valid CRC), by the documented layout."""
    meta = json.dumps(fields, separators=(",", ":")).encode()
    head = struct.pack("<8sHHI", b"SOGMTILE", 1, 0, len(meta)) + meta
    return head + struct.pack("<I", zlib.crc32(head)) + payload


_BAD_APPLIED: list[tuple[str, Any]] = [
    ("a list", [["k", [1.0, 2]]]),
    ("a string", "k"),
    ("a mark that is not a pair", {"k": [1.0]}),
    ("a mark that is a dict", {"k": {"stamp": 1.0, "digest": 2}}),
    ("a string stamp", {"k": ["1.0", 2]}),
    ("a boolean stamp", {"k": [True, 2]}),
    ("a NaN stamp", {"k": [float("nan"), 2]}),
    ("an infinite stamp", {"k": [float("inf"), 2]}),
    ("a negative digest", {"k": [1.0, -1]}),
    ("a digest of 2**64", {"k": [1.0, 2**64]}),
    ("a float digest", {"k": [1.0, 2.5]}),
    ("a boolean digest", {"k": [1.0, False]}),
    ("an empty key", {"": [1.0, 2]}),
    ("an over-long key", {"x" * (MAX_APPLIED_KEY + 1): [1.0, 2]}),
    ("too many entries", {f"k{n}": [1.0, n] for n in range(MAX_APPLIED + 1)}),
]


def test_marks_survive_the_file_format_exactly() -> None:
    data = _stack(1)
    blob = tile_to_bytes(tile_header(EXPECT, 2, -3, ["a", "b"], 20.0, applied=MARKS), data)
    fields, _ = _json_header(blob)
    # What the file says, by the spec: {key: [stamp, digest]}, digests as exact JSON integers.
    assert fields["applied"] == {k: [t, d] for k, (t, d) in MARKS.items()}
    tile = tile_from_bytes(blob, EXPECT)
    assert dict((k, (t, d)) for k, t, d in tile.header.applied) == MARKS
    loaded = tile.as_loader_result()
    assert len(loaded) == 5 and loaded[3] == {} and loaded[4] == MARKS
    assert np.array_equal(loaded[1], data)


def test_a_tile_without_marks_is_written_exactly_as_before() -> None:
    data = _stack(2)
    before = tile_header(EXPECT, 0, 0, ["a", "b"], 3.0)
    blob = tile_to_bytes(tile_header(EXPECT, 0, 0, ["a", "b"], 3.0, applied={}), data)
    fields, _ = _json_header(blob)
    assert "applied" not in fields
    assert before.applied == ()
    loaded = tile_from_bytes(blob, EXPECT).as_loader_result()
    assert len(loaded) == 3  # the old triple: loaders of old shape unchanged


def test_the_writer_keeps_only_marks_a_reader_accepts() -> None:
    """More than MAX_APPLIED marks: the newest by stamp are kept (never a file a reader would
    refuse); a mark with a NaN stamp, an empty or over-long key, or a digest outside 64 bits
    is left out."""
    many: dict[str, Mark] = {f"k{n:05d}": (float(n), n) for n in range(MAX_APPLIED + 100)}
    bad: dict[str, Mark] = {"nan": (float("nan"), 1), "": (1.0, 1),
                            "x" * (MAX_APPLIED_KEY + 1): (1.0, 1), "big": (1.0, 2**64),
                            "neg": (1.0, -1)}
    header = tile_header(EXPECT, 0, 0, ["a"], 1.0, applied={**many, **bad})
    assert len(header.applied) == MAX_APPLIED
    assert {k for k, _, _ in header.applied} == {f"k{n:05d}" for n in range(100, MAX_APPLIED
                                                                              + 100)}
    tile = tile_from_bytes(tile_to_bytes(header, _stack(3, 1)), EXPECT)
    assert len(tile.header.applied) == MAX_APPLIED


@pytest.mark.parametrize(("what", "bad"), _BAD_APPLIED, ids=[w for w, _ in _BAD_APPLIED])
def test_a_malformed_applied_field_is_refused(what: str, bad: Any) -> None:
    fields, payload = _json_header(tile_to_bytes(tile_header(EXPECT, 0, 0, ["a"], 1.0),
                                                 _stack(4, 1)))
    fields["applied"] = bad
    with pytest.raises(TileFormatError, match="applied"):
        tile_from_bytes(_forge(fields, payload), EXPECT)
    fields["applied"] = {"k": [1.0, 2]}  # the forging itself is sound: a good field loads
    assert tile_from_bytes(_forge(fields, payload), EXPECT).header.applied == (("k", 1.0, 2),)


def test_non_string_keys_cannot_reach_the_reader_but_are_refused() -> None:
    """JSON object keys are strings: a header can only say ``{"1": ...}``, which is a key.  The
    check stands for readers given other JSON (a number key is refused)."""
    from sogm_service.wire import tilefile as fmt
    with pytest.raises(TileFormatError, match="applied"):
        fmt._applied_field({"applied": {1: [1.0, 2]}})


def test_a_tile_with_a_bad_applied_field_is_quarantined(tmp_path: Path) -> None:
    with DirectoryStore(tmp_path, "lab", MARK_RES, MARK_T, frame="map") as store:
        store.write(1, 0, ["a"], _stack(5, 1), 1.0, applied={"k": (1.0, 2)})
        fields, payload = _json_header(tile_to_bytes(tile_header(EXPECT, 0, 0, ["a"], 1.0),
                                                     _stack(6, 1)))
        fields["applied"] = {"k": [float("nan"), 2]}
        bad = tmp_path / tile_file_name("lab", MARK_RES, MARK_T, 0, 0)
        bad.write_bytes(_forge(fields, payload))
        assert set(store.index()) == {(1, 0)}  # the header is checked when indexing
        assert not bad.exists() and (tmp_path / QUARANTINE_DIR / bad.name).exists()
        reason = (tmp_path / QUARANTINE_DIR / (bad.name + ".reason.txt")).read_text()
        assert "applied" in reason
        [problem] = store.problems
        assert problem.path == bad and "applied" in problem.reason
        assert store.load(0, 0) is None
        good = store.load(1, 0)
        assert good is not None and good.header.applied == (("k", 1.0, 2),)
