"""zstd payloads are bounded before any work: a frame is expanded only when it declares exactly
the size its message's header implies (an ISM) or at most a limit (a reply)."""

from __future__ import annotations

import numpy as np
import pytest
import zstandard

from sogm_service.wire import codec
from sogm_service.wire import compression as zstd
from sogm_service.wire.errors import DECODE_CODES, DecodeError
from sogm_service.wire.messages import IsmMessage


def _ism(cells: bytes, width: int, height: int, encoding: str = "prob_u8",
         compression: str | None = None) -> bytes:
    return codec.encode(IsmMessage.model_construct(
        layer=None, frame="map", stamp=0.0, robot=None, resolution=0.05,
        origin=IsmMessage.model_fields["origin"].default, width=width, height=height,
        encoding=encoding, data=cells, compression=compression))


@pytest.mark.parametrize("encoding,dtype", [("prob_u8", np.uint8), ("occupancy_i8", np.int8),
                                            ("prob_f32", np.float32), ("prob_u8_v2", np.uint8)])
def test_a_compressed_ism_decodes_to_the_raw_one(encoding: str, dtype: type) -> None:
    rng = np.random.default_rng(3)
    cells = (rng.integers(0, 101, (60, 90)) if dtype is not np.float32
             else rng.random((60, 90))).astype(dtype)
    raw = IsmMessage(resolution=0.05, width=90, height=60, encoding=encoding,
                     data=cells.tobytes())
    sent = raw.compressed()
    assert sent.compression == "zstd" and sent.data != raw.data
    got = codec.decode(IsmMessage, codec.encode(sent))
    assert got == raw  # the raw cells, compression None: the rest of the pipeline is unchanged


def test_grids_compress_many_times() -> None:
    grid = np.full((256, 256), 128, np.uint8)
    grid[100:110] = 250  # a wall through unknown
    raw = IsmMessage(resolution=0.05, width=256, height=256, encoding="prob_u8",
                     data=grid.tobytes())
    assert len(codec.encode(raw)) > 50 * len(codec.encode(raw.compressed()))


def _code(payload: bytes) -> str:
    with pytest.raises(DecodeError) as err:
        codec.decode(IsmMessage, payload)
    return err.value.code


def test_a_frame_that_claims_more_than_the_header_is_refused_unexpanded() -> None:
    bomb = zstandard.ZstdCompressor().compress(bytes(200_000_000))  # 200 MB of zeros: ~6 kB
    assert len(bomb) < 100_000
    assert _code(_ism(bomb, 10, 10, compression="zstd")) == "data_length"


def test_a_frame_without_its_size_garbage_and_trailing_frames_are_bad_compression() -> None:
    cells = bytes(100)
    sizeless = zstandard.ZstdCompressor(write_content_size=False).compress(cells)
    assert _code(_ism(sizeless, 10, 10, compression="zstd")) == "bad_compression"
    assert _code(_ism(b"not zstd at all", 10, 10, compression="zstd")) == "bad_compression"
    one = zstd.compress(cells)
    assert _code(_ism(one + one, 10, 10, compression="zstd")) == "bad_compression"
    assert "bad_compression" in DECODE_CODES


def test_the_header_is_priced_before_the_data_is_looked_at() -> None:
    """A grid over the cell limit is refused as too large whatever its data holds."""
    assert _code(_ism(b"garbage", 100_000, 100_000, compression="zstd")) == "too_large"


def test_an_unknown_compression_is_refused() -> None:
    assert _code(_ism(bytes(100), 10, 10, compression="lz4")) == "invalid_value"


def test_a_reply_frame_is_bounded_by_the_askers_limit() -> None:
    frame = zstd.compress(bytes(1000))
    assert zstd.decompress_at_most(frame, 1000) == bytes(1000)
    with pytest.raises(DecodeError) as err:
        zstd.decompress_at_most(frame, 999)
    assert err.value.code == "too_large"


def test_threads_compress_at_once() -> None:
    """A zstd compressor shared by threads crashes the process; each thread has its own."""
    import threading

    blobs = [np.random.default_rng(k).integers(0, 4, 1 << 19, dtype=np.uint8).tobytes()
             for k in range(4)]
    out: list[list[bytes]] = [[] for _ in blobs]

    def work(k: int) -> None:
        for _ in range(100):
            out[k].append(zstd.compress(blobs[k]))

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(blobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k, frames in enumerate(out):
        assert len(frames) == 100
        assert zstd.decompress(frames[-1], len(blobs[k])) == blobs[k]


def test_threads_decompress_at_once_and_a_bad_frame_leaves_the_next_one_whole() -> None:
    """Each thread reuses its own decompressor: a corrupt or cut frame refused on it does not
    spoil the frames it decompresses next."""
    import threading

    blobs = [np.random.default_rng(k).integers(0, 4, 1 << 16, dtype=np.uint8).tobytes()
             for k in range(4)]
    frames = [zstd.compress(b) for b in blobs]
    corrupt = bytearray(frames[0])
    corrupt[len(corrupt) // 2:] = bytes(len(corrupt) - len(corrupt) // 2)
    codes: list[list[str]] = [[] for _ in blobs]
    whole: list[bool] = [True for _ in blobs]

    def work(k: int) -> None:
        for bad in (bytes(corrupt), frames[k][:-5], frames[k] + frames[k]) * 30:
            try:
                zstd.decompress(bad, len(blobs[0]))
            except DecodeError as exc:
                codes[k].append(exc.code)
            whole[k] &= zstd.decompress(frames[k], len(blobs[k])) == blobs[k]

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(blobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(whole)
    assert all(c == ["bad_compression"] * 90 for c in codes), codes
