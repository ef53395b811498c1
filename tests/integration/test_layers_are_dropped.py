"""Evidence taken back: ``MapClient.drop_layers`` and ``sogm-service layers drop`` on a real
server process with a tile store.

Two robots map overlapping tiles under a memory budget so small that most tiles live only in
the store; dropping ``robot2/*`` leaves robot1's sub-map bit for bit as it was, removes
robot2's layers from ``info``, from every tile file and from the map a restarted server (after
a SIGKILL right after the reply) loads; tiles only robot2 had written are gone.  Both stores:
a directory, and an S3 bucket on a real SeaweedFS (tests/s3server.py).  A class
(``*/laser/obstacle``) then reads robot1's layer alone.  A key that carries no pattern is
refused with a code, a counter and one log line, and changes nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.core.geometry import Pose2D
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.s3 import S3Store
from sogm_service.wire.errors import ServiceError
from tests.conftest import ServerProcess, start_server, wait_processed, wait_until
from tests.s3server import BUCKET

pytestmark = pytest.mark.integration

RES, T = 0.5, 16  # tiles of 8 m
ROBOT1 = ["robot1/camera/person", "robot1/laser/obstacle"]
ROBOT2 = ["robot2/laser/obstacle"]
WINDOW: dict[str, Any] = dict(x=20.0, y=4.0, width=40.0, height=8.0, resolution=RES,
                              interp="nearest", encoding="logodds_i16")


def sections(tmp_path: Path, bucket: dict[str, Any] | None = None,
             ) -> dict[str, dict[str, Any]]:
    storage: dict[str, Any] = {"memory_budget_mb": 0.001, "checkpoint_interval_s": 0.2}
    out: dict[str, dict[str, Any]] = {"map": {"resolution": RES, "tile_size": T},
                                      "storage": storage}
    if bucket is None:
        storage["directory"] = str(tmp_path / "tiles")
    else:
        out["store"] = bucket
    return out


@pytest.fixture(params=["directory", pytest.param("s3", marks=pytest.mark.slow)])
def bucket(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch,
           ) -> dict[str, Any] | None:
    """None: a store directory; else a fresh prefix of the SeaweedFS test bucket (the AWS
    environment the servers inherit set)."""
    if request.param == "directory":
        return None
    seaweedfs = request.getfixturevalue("seaweedfs")
    for name, value in seaweedfs.env.items():
        monkeypatch.setenv(name, value)
    return {"url": f"s3://{BUCKET}/{seaweedfs.new_prefix()}/drops",
            "endpoint_url": seaweedfs.endpoint_url}


def publish_fleet(client: MapClient) -> None:
    """robot1 over tiles 0-2 (two layers), robot2 over tiles 1-4 (one layer): tiles 3 and 4
    hold robot2's evidence only."""
    rng = np.random.default_rng(7)

    def grid(w: int) -> np.ndarray:
        return rng.integers(0, 101, size=(16, w)).astype(np.int8)

    client.publish_ism("ism/robot1/laser/obstacle", grid(48), resolution=RES,
                       origin=Pose2D(0.0, 0.0, 0.0), stamp=100.0)
    client.publish_ism("ism/robot1/camera/person", grid(12), resolution=RES,
                       origin=Pose2D(1.0, 0.0, 0.0), stamp=100.0)
    client.publish_ism("ism/robot2/laser/obstacle", grid(64), resolution=RES,
                       origin=Pose2D(8.0, 0.0, 0.0), stamp=101.0)


def robot1_map(client: MapClient) -> np.ndarray:
    return np.asarray(client.submap(layers=ROBOT1, **WINDOW).data)


def stored_layers(tmp_path: Path, bucket: dict[str, Any] | None = None,
                  ) -> dict[tuple[int, int], list[str]]:
    """Each stored tile's layers, read from the directory or the bucket (read-only)."""
    store: DirectoryStore | S3Store = \
        DirectoryStore(tmp_path / "tiles", "default", RES, T, readonly=True) if bucket is None \
        else S3Store(bucket["url"], "default", RES, T, readonly=True,
                     endpoint_url=bucket["endpoint_url"])
    return {index: list(info.header.layers) for index, info in sorted(store.index().items())}


def test_dropping_robot2_leaves_robot1s_map_exactly(tmp_path: Path,
                                                    bucket: dict[str, Any] | None) -> None:
    server = start_server(tmp_path, sections(tmp_path, bucket))
    try:
        with MapClient.connect(server.endpoint, timeout=10.0) as client:
            publish_fleet(client)
            assert wait_processed(client, 3).get("isms_fused") == 3, server.log()
            assert wait_until(lambda: client.stats().counters.get("tiles_evicted", 0) >= 3, 30)
            before = robot1_map(client)
            assert sorted(client.info().layers) == sorted(ROBOT1 + ROBOT2)
            assert np.count_nonzero(before) > 900  # of 48 x 16 + 12 x 16 cells

            reply = client.drop_layers("robot2/*")
            assert reply.layers == ROBOT2 and reply.pattern == "robot2/*"
            assert reply.tiles_removed == 2  # tiles 3 and 4: robot2's only
            assert reply.tiles_rewritten == 4  # tiles 1-4 lost a plane (3 and 4 every one)
            assert reply.stored
            # What the store holds when the reply comes: no file carries robot2's layer.
            on_disk = stored_layers(tmp_path, bucket)
            assert sorted(on_disk) == [(0, 0), (1, 0), (2, 0)]
            assert all(set(layers) <= set(ROBOT1) for layers in on_disk.values())

            info = client.info()
            assert sorted(info.layers) == ROBOT1
            assert sorted(map(tuple, info.tiles)) == [(0, 0), (1, 0), (2, 0)]
            assert np.array_equal(robot1_map(client), before)  # bit for bit
            with pytest.raises(ServiceError) as gone:
                client.submap(layers=ROBOT2, **WINDOW)
            assert gone.value.code == "unknown_layer"
            # The class of every robot's laser obstacles now reads robot1's layer alone.
            laser = client.submap(layers=["*/laser/obstacle"], **WINDOW)
            assert np.array_equal(np.asarray(laser.data)[0], before[1])
            counters = client.stats().counters
            assert counters["layers_dropped"] == 1
            assert counters["drop_tiles_removed"] == 2
            # Asked again: nothing left to drop, not an error.
            again = client.drop_layers("robot2/*")
            assert again.layers == [] and again.tiles_rewritten == again.tiles_removed == 0
    finally:
        kill(server)  # a SIGKILL right after the reply: nothing is flushed at exit

    restarted = start_server(tmp_path, sections(tmp_path, bucket), name="restarted")
    try:
        with MapClient.connect(restarted.endpoint, timeout=10.0) as client:
            assert sorted(client.info().layers) == ROBOT1
            assert np.array_equal(robot1_map(client), before)
    finally:
        assert restarted.terminate() == 0


def kill(server: ServerProcess) -> None:
    if server.proc.poll() is None:
        server.proc.kill()  # our own child, by its pid
        server.proc.wait(10)


def test_cli_drop_and_a_refused_key(tmp_path: Path) -> None:
    server = start_server(tmp_path, sections(tmp_path))
    try:
        with MapClient.connect(server.endpoint, timeout=10.0) as client:
            publish_fleet(client)
            wait_processed(client, 3)
            before = robot1_map(client)
            # A key that carries no layer pattern: refused from the key, before any work.
            replies = list(client.session.get("sogm/default/drop/robot2/a%b", timeout=5.0))
            assert len(replies) == 1 and replies[0].err is not None
            assert b"bad_parameter" in replies[0].err.payload.to_bytes()
            assert client.stats().counters.get("query_errors_bad_parameter") == 1
            assert sorted(client.info().layers) == sorted(ROBOT1 + ROBOT2)
            assert server.log().count("layer drop refused (bad_parameter)") == 1

            out = subprocess.run(
                [sys.executable, "-m", "sogm_service", "layers", "drop", "robot1/camera/*",
                 "--connect", server.endpoint, "--json"],
                capture_output=True, text=True, timeout=60, check=False)
            assert out.returncode == 0, out.stderr
            reply = json.loads(out.stdout)
            assert reply["layers"] == ["robot1/camera/person"] and reply["stored"] is True
            assert sorted(client.info().layers) == ["robot1/laser/obstacle", *ROBOT2]
            laser = np.asarray(client.submap(layers=["robot1/laser/obstacle"], **WINDOW).data)
            assert np.array_equal(laser[0], before[1])
            assert all("robot1/camera/person" not in layers
                       for layers in stored_layers(tmp_path).values())
    finally:
        assert server.terminate() == 0


def test_a_cluster_member_refuses_to_drop(tmp_path: Path) -> None:
    cluster = {"map": {"resolution": RES, "tile_size": T},
               "cluster": {"enabled": True, "replicas": 1, "fetch_cache_s": 0.0}}
    server = start_server(tmp_path, cluster)
    try:
        with MapClient.connect(server.endpoint, timeout=10.0) as client:
            publish_fleet(client)
            wait_processed(client, 3)
            before = robot1_map(client)
            with pytest.raises(ServiceError) as refused:
                client.drop_layers("robot2/*")
            assert refused.value.code == "cluster_unsupported"
            assert client.stats().counters.get("query_errors_cluster_unsupported") == 1
            assert sorted(client.info().layers) == sorted(ROBOT1 + ROBOT2)
            assert np.array_equal(robot1_map(client), before)
            assert server.log().count("layer drop refused (cluster_unsupported)") == 1
    finally:
        assert server.terminate() == 0
