"""Layers that forget (core/map/forget): decay toward unknown with a half-life, lazily per tile.

Expected values are computed here from the rule (:mod:`sogm_service.core.map.forget`): a read at
``now`` gives ``trunc(l * 0.5 ** ((now - t_d) / h))`` (float64, toward zero); a write at ``t``
first decays the tile's layer in place by ``0.5 ** ((t - t_d) / h)`` when ``t - t_d >= h / 32``.
"""

from __future__ import annotations

import json
import math
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map import forget
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.config import ServiceConfig
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.format import read_tile_file
from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.tilefile import (
    FORMAT_VERSION,
    Expectation,
    parse_header,
    tile_from_bytes,
    tile_header,
    tile_to_bytes,
)
from tests.unit.store.test_format import GOLDEN

H = 10.0  # half-life (s) of "people"
BOX = (0, 0, 4, 4)


def new_map(loader=None) -> TiledMap:  # type: ignore[no-untyped-def]
    tiled = TiledMap("m", "map", TileLattice(1.0, 16), loader=loader)
    tiled.set_forget({"people": H, "*/carts": 2 * H})
    return tiled


def put(tiled: TiledMap, layer: str, value: int, stamp: float, x: int = 0, y: int = 0) -> None:
    """One aligned 1x1 ISM of increment ``value`` at cell (x, y) (added exactly, no resampling)."""
    tiled.fuse(layer, np.array([[value]], dtype=np.int16),
               GridGeometry(1.0, 1, 1, Pose2D(float(x), float(y), 0.0)), stamp=stamp)


def cell(tiled: TiledMap, layer: str, now: float | None = None, x: int = 0, y: int = 0) -> int:
    return int(tiled.mosaic(BOX, [tiled.layer_id(layer)], now)[0, y, x])


def expect(l: int, dt: float, h: float = H) -> int:
    return math.trunc(l * 0.5 ** (dt / h)) if dt > 0 else l


def test_rules_match_names_then_patterns() -> None:
    rules = forget.ForgetRules({"robot1/people": 5.0, "*/people": 30.0})
    assert rules.half_life("robot1/people") == 5.0
    assert rules.half_life("robot2/people") == 30.0
    assert rules.half_life("robot2/people2") is None
    with pytest.raises(ValueError):
        forget.ForgetRules({"x": 0.0})
    with pytest.raises(ValueError):
        forget.ForgetRules({"x": math.inf})


def test_decay_rounds_toward_zero() -> None:
    a = np.array([1000, -1000, 3, -3, 1, 0, 16000], dtype=np.int16)
    f = 0.5 ** 1.5
    assert forget.decayed(a, f).tolist() == [353, -353, 1, -1, 0, 0, 5656]
    assert forget.decay_factor(-1.0, H) == 1.0 and forget.decay_factor(H, H) == 0.5


def test_a_read_decays_by_elapsed_half_lives_and_other_layers_stay() -> None:
    tiled = new_map()
    put(tiled, "people", 1000, 100.0)
    put(tiled, "people", -1000, 100.0, x=1)
    put(tiled, "walls", 1000, 100.0)
    put(tiled, "robot1/carts", 1000, 100.0)
    assert cell(tiled, "people", 110.0) == 500
    assert cell(tiled, "people", 115.0) == expect(1000, 15.0) == 353
    assert cell(tiled, "people", 115.0, x=1) == -353
    assert cell(tiled, "people", 100.0) == 1000
    assert cell(tiled, "people", 90.0) == 1000  # never backwards
    assert cell(tiled, "walls", 1e6) == 1000
    assert cell(tiled, "robot1/carts", 120.0) == 500  # the pattern's 20 s half-life
    assert cell(tiled, "people", 100.0 + 40 * H) == 0  # exactly unknown in the end


def test_reads_default_to_the_map_clock_the_latest_stamp() -> None:
    tiled = new_map()
    put(tiled, "people", 1000, 100.0)
    assert tiled.now() == 100.0
    put(tiled, "walls", 7, 120.0, x=3)  # another layer's ISM moves the clock too
    assert tiled.now() == 120.0
    assert cell(tiled, "people") == 250
    window = GridGeometry(1.0, 2, 2, Pose2D(0.0, 0.0, 0.0))
    assert tiled.sample(window, ["people"])[0, 0, 0] == 250
    assert tiled.sample(window, ["people"], now=110.0)[0, 0, 0] == 500
    tiled.advance_clock(130.0)
    assert cell(tiled, "people") == 125
    tiled.advance_clock(50.0)  # never back
    assert tiled.now() == 130.0


def test_a_write_decays_the_tile_in_place_then_adds() -> None:
    tiled = new_map()
    put(tiled, "people", 1000, 100.0)
    put(tiled, "people", 400, 100.0, x=2)
    put(tiled, "people", 200, 110.0)
    snap = tiled.snapshot((0, 0))
    assert snap is not None
    lid = snap.layers.index("people")
    assert snap.data[lid, 0, 0] == 500 + 200
    assert snap.data[lid, 0, 2] == 200  # the whole tile's layer was decayed, not the ISM's cell
    assert snap.decay == {"people": 110.0}
    assert cell(tiled, "people", 120.0) == 350
    assert cell(tiled, "people", 120.0, x=2) == 100


def test_writes_closer_than_the_quantum_add_without_decaying() -> None:
    tiled = new_map()
    put(tiled, "people", 1000, 100.0)
    put(tiled, "people", 10, 100.0 + 0.9 * forget.QUANTUM * H)  # within h/32: no multiply
    assert cell(tiled, "people", 100.0 + 0.9 * forget.QUANTUM * H) \
        == expect(1010, 0.9 * forget.QUANTUM * H)
    assert cell(tiled, "people", 110.0) == 505  # decayed from 100: the ISM's stamp moved nothing
    put(tiled, "people", 10, 100.4)  # 0.4 s >= h/32 = 0.3125 s: multiply, then add
    snap = tiled.snapshot((0, 0))
    assert snap is not None
    assert snap.data[snap.layers.index("people"), 0, 0] == expect(1010, 0.4) + 10 == 992
    assert snap.decay == {"people": 100.4}


def test_an_older_ism_counts_as_old_as_it_is() -> None:
    tiled = new_map()
    put(tiled, "people", 1000, 110.0)
    put(tiled, "people", 100, 105.0)  # another robot's, 5 s late: half a half-life
    assert cell(tiled, "people", 110.0) == 1000 + expect(100, 5.0) == 1070
    assert cell(tiled, "people", 120.0) == expect(1070, 10.0) == 535
    put(tiled, "people", 100, 110.0 - 0.9 * forget.QUANTUM * H)  # within h/32: as it is
    assert cell(tiled, "people", 110.0) == 1170


def test_a_layers_first_write_starts_its_own_decay_whatever_other_layers_hold() -> None:
    """Robot b's layer written late into a tile robot a's layer wrote at 110: b's evidence
    from 100 reads decayed from 100, as it does where b's ISM came first (cluster members
    may receive two robots' ISMs in either order)."""
    late, early = new_map(), new_map()
    put(late, "a/carts", 500, 110.0)
    put(late, "people", 1000, 100.0)
    put(early, "people", 1000, 100.0)
    put(early, "a/carts", 500, 110.0)
    for tiled in (late, early):
        assert cell(tiled, "people", 110.0) == expect(1000, 10.0) == 500
    assert np.array_equal(late.snapshot((0, 0)).data, early.snapshot((0, 0)).data[::-1])


def test_robots_own_layers_give_the_same_bits_in_any_interleaving() -> None:
    """Each robot's ISMs in order, the robots interleaved at random: bit-identical maps."""
    rng = np.random.default_rng(3)
    robots = {f"r{k}/carts": [(int(v), float(t)) for v, t in zip(
        rng.integers(-3000, 3000, 12), np.sort(rng.uniform(0, 60, 12)), strict=True)]
        for k in range(3)}
    maps = []
    for _ in range(5):
        tiled, queues = new_map(), {name: list(isms) for name, isms in robots.items()}
        tiled.adopt_layers(sorted(robots))  # the same layer order everywhere
        while any(queues.values()):
            name = str(rng.choice([n for n, q in queues.items() if q]))
            value, stamp = queues[name].pop(0)
            put(tiled, name, value, stamp, x=int(stamp) % 4)
        maps.append(tiled.mosaic(BOX, [tiled.layer_id(n) for n in sorted(robots)], 60.0))
    for m in maps[1:]:
        assert np.array_equal(m, maps[0])


def test_frequent_writes_reach_exactly_unknown() -> None:
    # 4 Hz ISMs that say nothing about the cell (increment 0 elsewhere in the tile keeps it
    # touched): truncation cannot stall above 0 the way round-to-nearest would.
    tiled = new_map()
    put(tiled, "people", 700, 0.0)
    for k in range(1, 4 * 200):
        put(tiled, "people", 0, k / 4.0, x=3, y=3)
    snap = tiled.snapshot((0, 0))
    assert snap is not None and snap.data[snap.layers.index("people"), 0, 0] == 0
    # Round-to-nearest in place at the same steps would stall (the reason for truncation):
    l = 700.0
    for _ in range(0, 4 * 200, 8):  # multiplies every h/32 = 2 ISMs... at most every 0.3125 s
        l = float(np.rint(l * 0.5 ** (0.5 / H)))
    assert l > 0


def test_reads_never_change_the_map_even_interleaved() -> None:
    rng = np.random.default_rng(1)
    seq = [(int(rng.integers(-900, 900)), 100.0 + 0.7 * k, int(rng.integers(0, 4)),
            int(rng.integers(0, 4))) for k in range(60)]
    quiet, busy = new_map(), new_map()
    for value, stamp, x, y in seq:
        put(quiet, "people", value, stamp, x, y)
        put(busy, "people", value, stamp, x, y)
        busy.mosaic(BOX, [busy.layer_id("people")], stamp + 3.0)
        busy.sample(GridGeometry(0.7, 3, 3, Pose2D(0.3, 0.2, 0.4)), ["people"])
    a, b = quiet.snapshot((0, 0)), busy.snapshot((0, 0))
    assert a is not None and b is not None
    assert np.array_equal(a.data, b.data) and a.decay == b.decay


def test_concurrent_reads_leave_the_fused_state_bit_identical() -> None:
    seq = [(300 - 11 * k, 100.0 + 0.5 * k, k % 4, (k // 4) % 4) for k in range(200)]
    ref, live = new_map(), new_map()
    for value, stamp, x, y in seq:
        put(ref, "people", value, stamp, x, y)
    put(live, "people", 0, 99.0)
    stop = threading.Event()

    def reader() -> None:
        lid = live.layer_id("people")
        while not stop.is_set():
            live.mosaic(BOX, [lid])

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for t in threads:
        t.start()
    try:
        for value, stamp, x, y in seq:
            put(live, "people", value, stamp, x, y)
    finally:
        stop.set()
        for t in threads:
            t.join()
    a, b = ref.snapshot((0, 0)), live.snapshot((0, 0))
    assert a is not None and b is not None
    assert np.array_equal(a.data, b.data) and a.decay == b.decay


# -- persistence ----------------------------------------------------------------------------
def _store(tmp_path: Path) -> DirectoryStore:
    return DirectoryStore(tmp_path / "tiles", "m", 1.0, 16)


def test_decay_stamps_survive_eviction_and_restart(tmp_path: Path) -> None:
    store = _store(tmp_path)
    kept = new_map()
    evicted = new_map(loader=store.loader)
    for tiled in (kept, evicted):
        put(tiled, "people", 1000, 100.0)
        put(tiled, "walls", 800, 100.0, x=1)
        put(tiled, "people", 300, 104.0, x=2)
    evicted.evict((0, 0), before=lambda s: store.write(*s.index, s.layers, s.data, s.stamp,
                                                       s.decay))
    assert (0, 0) not in evicted.tiles
    for now in (104.0, 111.5, 130.0):
        assert np.array_equal(evicted.mosaic(BOX, [0, 1], now), kept.mosaic(BOX, [0, 1], now))
    put(kept, "people", 50, 112.0)
    put(evicted, "people", 50, 112.0)  # loads it back with its decay stamps, then decays
    a, b = kept.snapshot((0, 0)), evicted.snapshot((0, 0))
    assert a is not None and b is not None
    assert np.array_equal(a.data, b.data) and a.decay == b.decay == {"people": 112.0}
    # A checkpoint, then a restart: a fresh map over the same store reads the same.
    store.write(*b.index, b.layers, b.data, b.stamp, b.decay)
    store.close()
    again = _store(tmp_path)
    fresh = new_map(loader=again.loader)
    index = again.index()
    fresh.stored = set(index)
    for info in index.values():  # as the service's Checkpointer.attach does
        fresh.adopt_layers(info.header.layers)
    assert cell(fresh, "people", 120.0) == cell(kept, "people", 120.0) \
        == expect(expect(expect(1000, 4.0), 8.0) + 50, 8.0)


def test_the_header_field_is_optional_and_additive(tmp_path: Path) -> None:
    expect_ = Expectation("m", 1.0, 16, "map")
    data = np.zeros((2, 16, 16), dtype=np.int16)
    plain = tile_to_bytes(tile_header(expect_, 0, 0, ["people", "walls"], 5.0), data)
    fields = parse_header(plain)[1]
    assert "decay" not in fields  # tiles without decaying layers are written as before
    blob = tile_to_bytes(tile_header(expect_, 0, 0, ["people", "walls"], 5.0,
                                     decay={"people": 4.5}), data)
    header, fields, _ = parse_header(blob)
    assert FORMAT_VERSION == 1 and header.version == 1  # still version 1: old readers read it
    assert fields["decay"] == {"people": 4.5} and header.decay == (("people", 4.5),)
    # Everything a version-1 reader requires is there, unchanged.
    for key in ("map", "frame", "i", "j", "resolution", "tile_size", "layers", "stamp",
                "scale", "dtype", "shape", "raw_len", "payload_len", "payload_crc32"):
        assert key in fields
    loaded = tile_from_bytes(blob, expect_)
    assert loaded.as_loader_result()[3:] == ({"people": 4.5},)  # type: ignore[misc]


@pytest.mark.parametrize("bad", [{"nobody": 1.0}, {"people": "soon"}, {"people": True},
                                 ["people", 1.0]])
def test_a_bad_decay_field_is_refused(bad: object) -> None:
    expect_ = Expectation("m", 1.0, 16, "map")
    blob = tile_to_bytes(tile_header(expect_, 0, 0, ["people"], 5.0),
                         np.zeros((1, 16, 16), dtype=np.int16))
    _, fields, start = parse_header(blob)
    fields["decay"] = bad
    meta = json.dumps(fields, separators=(",", ":")).encode()
    import struct
    import zlib
    head = struct.pack("<8sHHI", b"SOGMTILE", 1, 0, len(meta)) + meta
    forged = head + struct.pack("<I", zlib.crc32(head)) + blob[start:]
    with pytest.raises(TileFormatError):
        tile_from_bytes(forged, expect_)


def test_golden_v1_tile_loads_and_its_decaying_layers_start_from_its_stamp(
        tmp_path: Path) -> None:
    store_dir = tmp_path / "golden"
    store_dir.mkdir()
    shutil.copy(GOLDEN, store_dir / GOLDEN.name)
    golden = read_tile_file(GOLDEN)
    assert golden.header.decay == ()
    store = DirectoryStore(store_dir, "golden", 0.05, 16, datum=None)
    tiled = TiledMap("golden", "map", TileLattice(0.05, 16), loader=store.loader)
    tiled.set_forget({"pallet": 60.0})
    tiled.stored = set(store.index())
    box = (3 * 16, -2 * 16, 16, 16)
    ids = [tiled.layer_id(n, create=True) for n in golden.header.layers]
    stamp = golden.header.stamp
    stored = np.clip(golden.data, *tiled.limits)  # the map clamps what it loads (eps0)
    at_stamp = tiled.mosaic(box, ids, stamp)
    assert np.array_equal(at_stamp, stored)
    later = tiled.mosaic(box, ids, stamp + 60.0)
    k = list(golden.header.layers).index("pallet")
    assert np.array_equal(later[k], np.trunc(stored[k] * 0.5).astype(np.int16))
    others = [n for n in range(3) if n != k]
    assert np.array_equal(later[others], stored[others])


# -- configuration --------------------------------------------------------------------------
def test_config_takes_half_lives_per_layer_pattern() -> None:
    cfg = ServiceConfig.model_validate({"map": {"forget": {"*/people": 30.0, "pallet": 600}}})
    assert cfg.map.forget == {"*/people": 30.0, "pallet": 600.0}
    assert ServiceConfig().map.forget == {}
    for bad in ({"people": 0.0}, {"people": -5.0}, {"": 3.0}, {"people": "x"}):
        with pytest.raises(ValidationError):
            ServiceConfig.model_validate({"map": {"forget": bad}})


# -- the service: config, queries and a restart ---------------------------------------------


def test_decaying_into_given_memory_gives_the_same_bits() -> None:
    rng = np.random.default_rng(8)
    state = rng.integers(-16000, 16001, (37, 41)).astype(np.int16)
    for factor in (0.0, 1e-9, 0.3, 0.5, 0.999, 1.0):
        out, work = np.empty_like(state), np.empty(state.shape, np.float64)
        assert np.array_equal(forget.decayed_into(state, factor, out, work),
                              forget.decayed(state, factor))
    with pytest.raises(ValueError):
        forget.decayed_into(state, 1.5, np.empty_like(state), np.empty(state.shape))


def test_a_fuse_into_a_decaying_layer_allocates_nothing_in_phase_2(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The decay on write and a late ISM's aged patch use memory taken in phase 1, so a
    MemoryError cannot strike between the first tile added and the last."""
    tiled = new_map()
    put(tiled, "people", 1000, 100.0)

    def refuse(*args: object) -> None:
        raise AssertionError("allocated in phase 2")

    monkeypatch.setattr(forget, "decayed", refuse)
    put(tiled, "people", 200, 110.0)  # decays the tile, then adds
    put(tiled, "people", 100, 105.0)  # late: its patch aged
    assert cell(tiled, "people", 110.0) == 500 + 200 + expect(100, 5.0)
