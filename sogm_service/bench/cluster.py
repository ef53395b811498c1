"""The cluster rows, with 2 ``sogm-service serve`` members of one map on this machine.

* ``cluster``: ingestion with 2 members (replicas 1) against 1 member.  Each member has
  ``[cluster] enabled``; one publisher session sends ``count`` 256x256 aligned ISMs spread over
  a 16 x 16 tile area; the time runs until every member has handled all of them (each receives
  every ISM and fuses its tiles only).
* ``cluster_submap``: the bench's 256x256x4 rotated biodds sub-map asked of the member that
  owns none of the window's tiles (it gathers them from the other, ``fetch_cache_s = 0`` so
  every query fetches) against the same query asked of their owner.
"""

from __future__ import annotations

import math
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.bench import transport
from sogm_service.bench.compute import synthetic_ism
from sogm_service.bench.core import Row, best_time, median, percentile
from sogm_service.bench.zbench import PY, WINDOW, Proc
from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import open_session, wait_listening
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.rendezvous import owners_of
from sogm_service.service.server.pipeline import ism_geometry
from sogm_service.wire import codec
from sogm_service.wire.keys import MapKeys
from sogm_service.wire.messages import IsmMessage, PoseModel

RES = 0.05


def _member(d: Path, name: str, peers: list[str], replicas: int,
            extra: str = "") -> tuple[Proc, str]:
    how = transport.current()
    endpoint = how.endpoint()
    cfg = d / f"{name}.toml"
    connect = ", ".join(f'"{p}"' for p in peers)
    cfg.write_text(f'[map]\nresolution = {RES}\n[cluster]\nenabled = true\nreplicas = {replicas}\n'
                   f'{extra}'
                   f'[zenoh]\nlisten = ["{endpoint}"]\nconnect = [{connect}]\n'
                   + how.server_toml(),
                   encoding="utf-8")
    proc = Proc([PY, "-m", "sogm_service", "serve", "--config", str(cfg)], d / f"{name}.log")
    wait_listening(endpoint, 30.0, lambda: proc.popen.poll() is not None, proc.tail)
    return proc, endpoint


def _wait(client: MapClient, members: int, n: int, timeout: float = 300.0) -> None:
    import msgpack
    import zenoh

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = 0
        for reply in client.session.get(client.key("stats"), target=zenoh.QueryTarget.ALL,
                                        consolidation=zenoh.ConsolidationMode.NONE,
                                        timeout=5.0):
            if reply.ok is not None:
                got = msgpack.unpackb(reply.ok.payload.to_bytes())
                done += got["counters"].get("isms_fused", 0) >= n
        if done >= members:
            return
        time.sleep(0.01)
    raise RuntimeError(f"members did not handle {n} ISMs in {timeout} s")


def _rate(members: int, count: int, rounds: int) -> list[float]:
    rng = np.random.default_rng(1)
    data = rng.integers(60, 200, size=(256, 256), dtype=np.uint8)
    with tempfile.TemporaryDirectory(prefix="sogm-bench-cluster-") as tmp:
        d = Path(tmp)
        procs: list[Proc] = []
        endpoints: list[str] = []
        try:
            for k in range(members):
                proc, ep = _member(d, f"m{k}", list(endpoints), replicas=1)
                procs.append(proc)
                endpoints.append(ep)
            pub = MapClient(open_session(transport.current().client(endpoints[0])))
            try:
                deadline = time.monotonic() + 60
                while len(pub.servers(timeout=1.0)) < members and time.monotonic() < deadline:
                    time.sleep(0.1)
                time.sleep(1.0)  # the members' own handovers settle
                rates = []
                sent = 0
                for _ in range(rounds + 1):  # the first round warms up
                    started = time.perf_counter()
                    for k in range(count):
                        ox, oy = (k * 7) % 16 * 12.8, (k * 3) % 16 * 12.8
                        pub.publish_ism(transport.current().ism_key("obstacle"), data,
                                        resolution=RES,
                                        origin=Pose2D(ox, oy, 0.0), stamp=float(sent + k))
                    sent += count
                    _wait(pub, members, sent)
                    rates.append(count / (time.perf_counter() - started))
                return rates[1:]
            finally:
                pub.close()
        finally:
            for proc in procs:
                proc.stop()


def cluster(quick: bool) -> Row:
    count, rounds = (200, 1) if quick else (1500, 3)
    one = _rate(1, count, rounds)
    two = _rate(2, count, rounds)
    ours, base = median(two), median(one)
    ratio = ours / base
    return Row("cluster_ingest", ours, base, "ISM/s", ratio, ">= 1.6x (report: 2 cores)", None,
               "one cluster member (replicas 1, default fuse workers)",
               f"2 members, replicas 1, each fusing its tiles of every ISM; median of {rounds} "
               f"bursts of {count} 256x256 ISMs; all processes share this machine's cores",
               {"count": float(count), "rounds": float(rounds)})


# -- cluster_submap ---------------------------------------------------------------------------
def _server_id(proc: Proc) -> str:
    """From serve's start line: ``sogm-service: serving map 'm' as <id> on ...``."""
    words = proc.expect("sogm-service:", 60.0)
    return words[words.index("as") + 1]


def _block_owned_by(owner: str, members: set[str]) -> tuple[int, int]:
    """A 2 x 2 block of tiles (its lower-left index) whose only owner is ``owner``."""
    for j in range(16):
        for i in range(16):
            block = [(i + di, j + dj) for di in (0, 1) for dj in (0, 1)]
            if all(owners_of(members, t, 1) == (owner,) for t in block):
                return i, j
    raise RuntimeError("no 2x2 block of tiles owned by one member in 16 x 16 tiles")


def _timed(client: MapClient, member: str, window: dict[str, Any], repeats: int
           ) -> list[float]:
    """Sub-map latencies (reply decoded) of one member, asked under its own key (which member
    a plain get reaches is Zenoh's routing choice, not the endpoint's)."""
    from sogm_service.wire import codec
    from sogm_service.wire.queries import GridReply

    key = MapKeys(client.prefix, client.map_name).member(member, "submap")
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        codec.decode(GridReply, client.get_raw(key, window))
        out.append(time.perf_counter() - t0)
    return out


def cluster_submap(quick: bool) -> Row:
    repeats = 20 if quick else 200
    with tempfile.TemporaryDirectory(prefix="sogm-bench-cluster-") as tmp:
        d = Path(tmp)
        extra = "fetch_cache_s = 0.0\n"
        a, a_ep = _member(d, "m0", [], 1, extra)
        procs = [a]
        try:
            b, b_ep = _member(d, "m1", [a_ep], 1, extra)
            procs.append(b)
            ids = {_server_id(a): a_ep, _server_id(b): b_ep}
            asker, owner = list(ids)
            i, j = _block_owned_by(owner, set(ids))
            how = transport.current()
            with MapClient.connect(timeout=10.0, zenoh_settings=how.client(ids[asker])) as far, \
                    MapClient.connect(timeout=10.0, zenoh_settings=how.client(ids[owner])) as near:
                deadline = time.monotonic() + 60
                while len(near.servers(timeout=1.0)) < 2 and time.monotonic() < deadline:
                    time.sleep(0.1)
                time.sleep(1.0)  # the members' handovers settle
                span = 256 * RES
                for k in range(4):  # 4 layers over the block (and nowhere else)
                    near.publish_ism(how.ism_key(f"layer{k}"), synthetic_ism(512, k),
                                     resolution=RES, origin=Pose2D(i * span, j * span, 0.0),
                                     stamp=float(k))
                _wait(near, 2, 4)
                window = {**WINDOW, "x": (i + 1) * span, "y": (j + 1) * span}
                ours, base = [], []
                served, served_owner = 0, 0  # tiles fetched for each member's queries
                for _ in range(3):  # interleaved thirds: load changes hit both alike
                    before = _served(near)
                    base += _timed(near, owner, window, repeats // 3 + 1)
                    middle = _served(near)
                    ours += _timed(far, asker, window, repeats // 3 + 1)
                    served_owner += middle - before
                    served += _served(near) - middle
        finally:
            for proc in procs:
                proc.stop()
    m_o, m_b = median(ours) * 1e3, median(base) * 1e3
    p_o, p_b = percentile(ours, 99) * 1e3, percentile(base, 99) * 1e3
    return Row("cluster_submap_non_owner", m_o, m_b, "ms", m_o / m_b, "report", None,
               "the same sub-map asked of the member that owns all its tiles",
               f"2 members, replicas 1, no fetch cache: each query through the non-owner "
               f"fetches the window's tiles from the owner ({served} tiles served for "
               f"{len(ours)} queries, {served_owner} for the owner's); each member asked "
               f"under its own key; prob_f32 reply decoded; p99 {p_o:.2f} vs {p_b:.2f} ms",
               {"p99_ms": p_o, "baseline_p99_ms": p_b, "tiles_served": float(served),
                "tiles_served_for_owner_queries": float(served_owner),
                "queries": float(len(ours))})


def _served(client: MapClient) -> int:
    """Tiles the owner served to the other member (``cluster_tiles_served``), summed."""
    import msgpack
    import zenoh

    total = 0
    for reply in client.session.get(client.key("stats"), target=zenoh.QueryTarget.ALL,
                                    consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
        if reply.ok is not None:
            got = msgpack.unpackb(reply.ok.payload.to_bytes())
            total += int(got["counters"].get("cluster_tiles_served", 0))
    return total


# -- cluster_split: the alternative to sending every ISM to every member ------------------------
def _parts(geom: GridGeometry, lattice: TileLattice) -> list[tuple[int, int, int, int]]:
    """The ISM-grid rectangles ``(u0, v0, u1, v1)`` (inclusive) holding every cell that
    overlaps each tile the ISM touches: what a per-tile split would send to that tile's
    owners (a rotated ISM's rectangles overlap)."""
    to_cell = geom.world_to_cell()
    span = lattice.span
    out = []
    for i, j in lattice.tiles_overlapping(geom):
        xs = np.array([i, i + 1, i + 1, i]) * span
        ys = np.array([j, j, j + 1, j + 1]) * span
        u = to_cell[0, 0] * xs + to_cell[0, 1] * ys + to_cell[0, 2]
        v = to_cell[1, 0] * xs + to_cell[1, 1] * ys + to_cell[1, 2]
        u0, u1 = max(0, math.ceil(u.min() - 0.5)), min(geom.width - 1, math.floor(u.max() + 0.5))
        v0, v1 = max(0, math.ceil(v.min() - 0.5)), min(geom.height - 1,
                                                      math.floor(v.max() + 0.5))
        if u0 <= u1 and v0 <= v1:
            out.append((u0, v0, u1, v1))
    return out


def _split_encoded(msg: IsmMessage, parts: list[tuple[int, int, int, int]]) -> list[bytes]:
    """Each part as an ISM of its own (same resolution and heading, origin moved)."""
    grid = msg.array()
    c, s, r = math.cos(msg.origin.yaw), math.sin(msg.origin.yaw), msg.resolution
    out = []
    for u0, v0, u1, v1 in parts:
        ox = msg.origin.x + c * u0 * r - s * v0 * r
        oy = msg.origin.y + s * u0 * r + c * v0 * r
        piece = np.ascontiguousarray(grid[v0:v1 + 1, u0:u1 + 1])
        out.append(codec.encode(msg.model_copy(update={
            "origin": PoseModel(x=ox, y=oy, yaw=msg.origin.yaw), "width": piece.shape[1],
            "height": piece.shape[0], "data": piece.tobytes()})))
    return out


def cluster_split(quick: bool) -> Row:
    """Bytes on the network per ISM: every member receives it whole (what the service does)
    against a split per tile sent to each tile's ``replicas`` owners only; and the
    publisher's CPU to split and encode against encoding it whole."""
    from sogm_service.bench.compute import ism_message

    count, replicas = (60 if quick else 400), 2
    rng = np.random.default_rng(3)
    lattice = TileLattice(RES, 256)
    msgs = []
    for k in range(count):
        x, y = (float(v) for v in rng.uniform(0.0, 100.0, 2))
        yaw = float(rng.uniform(-math.pi, math.pi))
        msgs.append(ism_message(synthetic_ism(256, k % 4), RES, Pose2D(x, y, yaw)))
    whole = [float(len(codec.encode(m))) for m in msgs]
    parts = [_parts(ism_geometry(m), lattice) for m in msgs]
    split = [float(sum(len(b) for b in _split_encoded(m, p)))
             for m, p in zip(msgs, parts, strict=True)]
    t_whole = median([best_time(partial(codec.encode, m)) for m in msgs])
    t_split = median([best_time(partial(_split_encoded, m, p))
                      for m, p in zip(msgs, parts, strict=True)])
    n_parts = median([float(len(p)) for p in parts])
    per_ism = {n: (n * median(whole), min(n, replicas) * median(split)) for n in (2, 3, 4, 8)}
    ours, base = per_ism[4][1], per_ism[4][0]
    return Row("cluster_split_bytes", ours / 1e3, base / 1e3, "kB/ISM", ours / base, "report",
               None, "every one of 4 members receives the whole ISM (what the service does)",
               f"{count} 256x256 prob_u8 ISMs at any heading; split per 256-cell tile into the "
               f"ISM-grid rectangles over each tile ({n_parts:.0f} "
               f"parts, {median(split) / median(whole):.2f}x the ISM's bytes), each sent to "
               f"its {replicas} owners; " + ", ".join(
                   f"{n} members: {b / 1e3:.0f} vs {w / 1e3:.0f} kB" for n, (w, b) in
                   per_ism.items()) + f"; publisher CPU to split and encode "
               f"{t_split * 1e3:.3f} ms vs {t_whole * 1e3:.3f} ms to encode whole",
               {"whole_bytes": float(median(whole)), "split_bytes": float(median(split)),
                "parts": n_parts,
                "split_encode_ms": t_split * 1e3, "whole_encode_ms": t_whole * 1e3})

