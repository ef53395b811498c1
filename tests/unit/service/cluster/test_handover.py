"""Applied marks persisted with each tile (issue 20): the last ISM fused into a tile per ISM key
(``Tile.applied``) goes into the tile file's ``applied`` header field and comes back when the
tile is loaded, so a cluster member serving an evicted tile, or restarted from its store, still
says which ISMs its copy holds, and a joiner's handover replays only the ISMs after them.

Malformed ``applied`` fields are forged from the file layout in ``store/format.py``'s docstring
(prefix, JSON header, CRC-32, payload), not with the project's encoder.
"""

from __future__ import annotations

import json
import struct
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, loopback_settings, open_session
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.rendezvous import Ownership
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.service.cluster.cluster import Cluster
from sogm_service.service.cluster.handover import replay_plan
from sogm_service.service.config import ServiceConfig
from sogm_service.service.server.checkpoints import Checkpointer
from sogm_service.service.server.fusers import FuseJob, FuseWorkers
from sogm_service.service.server.stats import Stats
from sogm_service.store.directory import QUARANTINE_DIR, DirectoryStore
from sogm_service.store.format import (
    MAX_APPLIED,
    MAX_APPLIED_KEY,
    Expectation,
    tile_file_name,
    tile_from_bytes,
    tile_header,
    tile_to_bytes,
)
from sogm_service.store.writer import TileWriter
from sogm_service.wire.errors import TileFormatError
from tests import test_cluster as cl
from tests.conftest import ServerProcess, start_server, wait_until

RES = 0.1
T = 16
EXPECT = Expectation("lab", RES, T, "map")
MARKS: dict[str, Mark] = {"sogm/lab/ism/r1/laser/obstacle": (12.5, 2**64 - 1),
                          "sogm/lab/ism/r2/laser/obstacle": (7.0, 0),
                          "sogm/lab/ism/r3/cam/people": (1700000000.25, 123456789)}


def _stack(seed: int, n: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(-3000, 3000, (n, T, T)).astype(np.int16)


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


# -- the file format ------------------------------------------------------------------------
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
    from sogm_service.store import format as fmt
    with pytest.raises(TileFormatError, match="applied"):
        fmt._applied_field({"applied": {1: [1.0, 2]}})


def test_a_tile_with_a_bad_applied_field_is_quarantined(tmp_path: Path) -> None:
    with DirectoryStore(tmp_path, "lab", RES, T, frame="map") as store:
        store.write(1, 0, ["a"], _stack(5, 1), 1.0, applied={"k": (1.0, 2)})
        fields, payload = _json_header(tile_to_bytes(tile_header(EXPECT, 0, 0, ["a"], 1.0),
                                                     _stack(6, 1)))
        fields["applied"] = {"k": [float("nan"), 2]}
        bad = tmp_path / tile_file_name("lab", RES, T, 0, 0)
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


# -- the map, the writer and the store ------------------------------------------------------
def _ism(rng: np.random.Generator, x: int, y: int) -> tuple[np.ndarray, GridGeometry]:
    """Mild, aligned increments (no cell near the clamp: Eq. 1 is exact integer addition)."""
    inc = rng.integers(-40, 41, (12, 20)).astype(np.int16)
    return inc, GridGeometry(RES, 20, 12, Pose2D(x * RES, y * RES, 0.0))


class _GatedStore(DirectoryStore):
    """A directory store whose writes wait for ``gate`` (a snapshot stays queued meanwhile)."""

    gate = threading.Event()

    def write(self, *args: Any, **kw: Any) -> Any:
        assert self.gate.wait(10.0)
        return super().write(*args, **kw)


def test_marks_survive_evict_and_load_back_through_writer_and_store(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    store = _GatedStore(tmp_path, "lab", RES, T, frame="map")
    store.gate = threading.Event()
    writer = TileWriter(store)
    tiled = TiledMap("lab", "map", TileLattice(RES, T), loader=writer.loader)
    try:
        for n, key in enumerate(["ism/r1", "ism/r2", "ism/r1"]):
            inc, geom = _ism(rng, 10, 4)  # spans tiles (0, 0) and (1, 0)
            tiled.fuse("l", inc, geom, "nearest", float(n + 1), mark=(key, (n + 1.0, 100 + n)))
        expected = {"ism/r1": (3.0, 102), "ism/r2": (2.0, 101)}
        for index in [(0, 0), (1, 0)]:
            assert tiled.tiles[index].applied == expected

        def submit(snap: Any) -> None:
            writer.submit(snap.index[0], snap.index[1], snap.layers, snap.data, snap.stamp,
                          token=snap.version, applied=snap.applied)

        # Evicted while its snapshot still waits for the disk: back from the writer's queue.
        tiled.evict((0, 0), before=submit)
        assert writer.is_pending(0, 0) and not store.path_for(0, 0).exists()
        again = tiled.get_tile((0, 0))
        assert again is not None and again.applied == expected
        store.gate.set()
        assert writer.flush(10.0)
        tiled.evict((0, 0), before=submit)
        tiled.evict((1, 0), before=submit)
        assert writer.flush(10.0) and not tiled.tiles
        for index in [(0, 0), (1, 0)]:  # now from the files
            tile = tiled.get_tile(index)
            assert tile is not None and tile.applied == expected
        # A restart: a new map over the same directory, marks from the files only.
        fresh = TiledMap("lab", "map", TileLattice(RES, T), loader=store.loader)
        fresh.stored = set(store.index())
        tile = fresh.get_tile((1, 0))
        assert tile is not None and tile.applied == expected
        # A further fuse updates one key's mark; the other comes from the file.
        inc, geom = _ism(rng, 10, 4)
        fresh.fuse("l", inc, geom, "nearest", 4.0, mark=("ism/r2", (4.0, 103)))
        assert tile.applied == {"ism/r1": (3.0, 102), "ism/r2": (4.0, 103)}
    finally:
        store.gate.set()
        writer.close(10.0)
        store.close()


# -- through the cluster's handover ---------------------------------------------------------
KEYS = ["ism/r1/laser/obstacle", "ism/r2/laser/obstacle"]


def _jobs(n: int) -> list[FuseJob]:
    """ISM number 1..n, alternating publishers, each spanning tiles (0, 0) and (1, 0)."""
    rng = np.random.default_rng(17)
    out = []
    for k in range(1, n + 1):
        inc, geom = _ism(rng, int(rng.integers(4, 14)), int(rng.integers(0, 4)))
        key = KEYS[k % 2]
        out.append(FuseJob(key.split("/")[1], inc, geom, "nearest", float(k),
                           lambda touched, error: None, key=key, digest=1000 + k))
    return out


def _planes(tiled: TiledMap) -> dict[tuple[TileIndex, str], bytes]:
    out = {}
    for index in tiled.known_tiles():
        tiled.get_tile(index)
        snap = tiled.snapshot(index)
        assert snap is not None
        for k, name in enumerate(snap.layers):
            if snap.data[k].any():
                out[(index, name)] = snap.data[k].tobytes()
    return out


def _config(tmp_path: Path | None, **storage: Any) -> ServiceConfig:
    sections: dict[str, Any] = {"map": {"name": "lab", "resolution": RES, "tile_size": T},
                                "cluster": {"enabled": True, "handover_timeout_s": 2.0}}
    if tmp_path is not None:
        sections["storage"] = {"directory": str(tmp_path), **storage}
    return ServiceConfig.model_validate(sections)


def _cluster(config: ServiceConfig, stats: Stats) -> tuple[Cluster, TiledMap, Checkpointer]:
    keeper = Checkpointer(config, stats, keep=set)
    tiled = TiledMap("lab", "map", TileLattice(RES, T), loader=keeper.load)
    keeper.attach(tiled)
    return Cluster(config, tiled, keeper, stats, FuseWorkers(tiled, 1), lambda t: True), \
        tiled, keeper


@pytest.fixture
def sessions() -> Iterator[list[Any]]:
    opened: list[Any] = []
    yield opened
    for s in opened:
        s.close()


def test_a_joiner_replays_only_isms_after_the_marks_of_an_evicted_restarted_owner(
        tmp_path: Path, sessions: list[Any]) -> None:
    """The owner fused ISMs 1-4, evicted every tile to its store (memory budget) and was
    restarted from that store; the joiner journaled ISMs 3-6 (it subscribed after ISM 2) and
    pulls both tiles from the owner over Zenoh (the real ``_on_tile``/``tile_answer`` and
    ``_pull``).  The marks come back from the files, so ISMs 3 and 4 are not fused twice: the
    joiner's tiles equal a map fused with 1-6 once each, bit for bit."""
    jobs = _jobs(6)
    reference = TiledMap("lab", "map", TileLattice(RES, T))
    for job in jobs:
        job.fuse(reference, None)

    stats = Stats()
    owner, tiled, keeper = _cluster(_config(tmp_path / "a", memory_budget_mb=1e-6), stats)
    for job in jobs[:4]:
        job.fuse(tiled, None)
    keeper.enforce_budget()  # the budget holds no tile: every one goes to the store
    assert not tiled.tiles and stats.snapshot()[0]["tiles_evicted"] == 2
    keeper.close(10.0)
    # Restart: a new member over the same store (no tile resident, marks only on disk).
    owner, tiled, keeper = _cluster(_config(tmp_path / "a", memory_budget_mb=1e-6), Stats())
    assert not tiled.tiles and tiled.stored == {(0, 0), (1, 0)}

    endpoint = free_tcp_endpoint()
    sa = open_session(loopback_settings(listen=endpoint))
    sessions.append(sa)
    sb = open_session(loopback_settings(connect=endpoint))
    sessions.append(sb)
    view = Ownership(frozenset({"a", "b"}), 2)
    owner._session, owner.me, owner._view = sa, "a", view
    sa_tile = sa.declare_queryable(owner.keys.key("cluster", "tile", "**"), owner._on_tile)
    joiner, joined, _ = _cluster(_config(None), Stats())
    joiner._session, joiner.me, joiner._view = sb, "b", view
    assert wait_until(lambda: joiner._fetch_one((0, 0), None, 1.0) is not None, 10)

    journal = jobs[2:]  # ISMs 3..6, in arrival order
    for index in [(0, 0), (1, 0)]:
        joiner._journal[index] = list(journal)
        assert joiner._pull(index, True) == 1
    assert joiner.stats.snapshot()[0]["cluster_isms_replayed"] == 4  # 5 and 6, per tile
    for index in [(0, 0), (1, 0)]:
        held = joined.tiles[index].applied
        assert held == {KEYS[0]: (6.0, 1006), KEYS[1]: (5.0, 1005)}
    assert _planes(joined) == _planes(reference)

    # What the marks prevent: the copy without them (as before they were stored) replays all
    # four journaled ISMs, and 3 and 4 end up fused twice.
    keep, _ = replay_plan(journal, {})
    assert len(keep) == 4
    unmarked = TiledMap("lab", "map", TileLattice(RES, T))
    for job in jobs[:4] + keep:
        job.fuse(unmarked, None)
    assert _planes(unmarked) != _planes(reference)
    sa_tile.undeclare()
    keeper.close(10.0)


def test_the_replay_plan_with_stored_marks_neither_loses_nor_repeats(tmp_path: Path) -> None:
    """Unit level: marks written with a tile and read back give the same plan as the live
    marks did."""
    jobs = _jobs(6)
    tiled = TiledMap("lab", "map", TileLattice(RES, T))
    for job in jobs[:4]:
        job.fuse(tiled, None)
    live = tiled.tiles[(0, 0)].applied
    with DirectoryStore(tmp_path, "lab", RES, T, frame="map") as store:
        snap = tiled.snapshot((0, 0))
        assert snap is not None
        store.write(0, 0, snap.layers, snap.data, snap.stamp, applied=snap.applied)
        loaded = store.loader(0, 0)
    assert loaded is not None and len(loaded) == 5
    stored = loaded[4]
    assert stored == live
    keep, skip = replay_plan(jobs[1:], stored)
    assert [j.stamp for j in keep] == [5.0, 6.0] and not skip


# -- two member processes -------------------------------------------------------------------
def _small_member(tmp_path: Path, name: str, peers: list[ServerProcess],
                  servers: int) -> ServerProcess:
    """A cluster member (tile size and resolution of test_cluster) whose memory budget holds
    about one tile, so it evicts nearly every tile it fuses (outside the robots' own tiles)."""
    sections: dict[str, dict[str, Any]] = {
        "map": {"resolution": cl.RES, "tile_size": cl.TILE},
        "cluster": {"enabled": True, "replicas": 2, "fetch_cache_s": 0.0},
        "storage": {"directory": str(tmp_path / f"store-{name}"),
                    "checkpoint_interval_s": 0.5, "memory_budget_mb": 0.002},
        "tiles": {"roi_radius_tiles": 0},
        "zenoh": {"listen": [free_tcp_endpoint()], "connect": [p.endpoint for p in peers]},
    }
    return start_server(tmp_path, sections, name=name, servers=servers, wait=40.0)


@pytest.mark.flaky(reruns=2)
@pytest.mark.timeout(180)
def test_a_joiner_pulling_evicted_tiles_equals_a_single_server(
        tmp_path: Path, procs: list[ServerProcess]) -> None:
    """Member a evicts nearly every tile (memory budget) while the fleet publishes; member b
    joins while the fleet keeps publishing (so its journal holds ISMs a's evicted copies
    already have) and pulls every tile from a (replicas 2 over 2 members: both own all).
    b's map equals a single reference server's bit for bit: no ISM lost, none fused twice."""
    a = _small_member(tmp_path, "a", [], 1)
    procs.append(a)
    ref = cl._reference(tmp_path, [a])
    procs.append(ref)
    fleet = cl.Fleet(a.endpoint, seed=23)
    observer = MapClient.connect(a.endpoint, timeout=5.0)
    try:
        assert wait_until(lambda: fleet.linked(a, ref), 30)
        fleet.publish(4)
        assert wait_until(lambda: cl._all_fused(observer, fleet.sent, 1), 60)
        assert observer.stats().counters.get("tiles_evicted", 0) > 0
        stop = threading.Event()

        def publish_meanwhile() -> None:
            while not stop.is_set():
                fleet.publish(1)
                stop.wait(0.15)

        publisher = threading.Thread(target=publish_meanwhile)
        publisher.start()
        try:
            b = _small_member(tmp_path, "b", [a], 2)
            procs.append(b)
            stop.wait(1.0)  # and a little after b declared itself
        finally:
            stop.set()
            publisher.join(30)
        assert wait_until(lambda: cl._all_fused(observer, 0, 2), 60)
        stats = cl._member_stats(observer)
        joined = next(st for st in stats.values()
                      if st["counters"].get("cluster_tiles_pulled", 0) > 0)
        assert joined["counters"].get("isms_fused", 0) < fleet.sent  # it did join late
        expected = cl._reference_map(ref, fleet.sent)
        assert np.abs(expected).sum() > 0
        # b's own ISMs after the join may still be on their way: wait for them, then the
        # comparison is exact (a tile fused twice never comes back to equal).
        assert wait_until(lambda: max(st["counters"].get("isms_fused", 0)
                                      for st in cl._member_stats(observer).values())
                          >= fleet.sent, 60)
        assert wait_until(lambda: np.array_equal(cl._submap(b.endpoint), expected), 30), \
            "the joined member's map differs from the single server's"
        assert np.array_equal(cl._submap(a.endpoint), expected)
    finally:
        observer.close()
        fleet.close()


def test_a_sent_tile_carries_stamp_decay_and_marks_and_a_wrong_one_is_refused() -> None:
    """What replicas and cluster members send each other (``TileFiles``): the receiver gets
    the sender's stamp, decay stamps and marks; a tile answered for another index, or
    damaged, is refused and changes nothing."""
    from sogm_service.service.cluster.replication import TileFiles
    from sogm_service.wire.errors import TileFormatError

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
