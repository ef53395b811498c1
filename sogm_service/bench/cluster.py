"""The ``cluster`` row: ingestion with 2 members (replicas 1) against 1 member, same machine.

Each member is a ``sogm-service serve`` process with ``[cluster] enabled``; one publisher
session sends ``count`` 256x256 aligned ISMs spread over a 16 x 16 tile area; the time runs
until every member has handled all of them (each receives every ISM and fuses its tiles only).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from sogm_service.bench import transport
from sogm_service.bench.core import Row, median
from sogm_service.bench.zbench import PY, Proc
from sogm_service.core.geometry import Pose2D
from sogm_service.service.client import MapClient
from sogm_service.service.session import open_session, wait_listening

RES = 0.05


def _member(d: Path, name: str, peers: list[str], replicas: int) -> tuple[Proc, str]:
    how = transport.current()
    endpoint = how.endpoint()
    cfg = d / f"{name}.toml"
    connect = ", ".join(f'"{p}"' for p in peers)
    cfg.write_text(f'[map]\nresolution = {RES}\n[cluster]\nenabled = true\nreplicas = {replicas}\n'
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
