"""A cluster on one shared object store: three members behind a router with ``[store] url``
on a real SeaweedFS (tests/s3server.py) and no disk of their own.

* Killing every member and starting one fresh member on the bucket gives the map back: its
  sub-map equals the one before (every tile had been written: the flush interval is what a
  crash may lose), and no member deleted the tiles it stopped owning from the shared bucket.
* A member joining while the bucket's copies are behind the members' memory loads its tiles
  from the bucket: their owners write them there for it.
* Checkpoints write a tile on its primary only: a member killed before it wrote its tiles
  leaves them to the member that becomes their primary, which writes them.
* A member stopped with SIGSTOP while the others take over and fuse newer ISMs, then resumed
  and shut down (which flushes its stale tiles), overwrites none of the newer tiles: its writes
  are fenced by the objects' ETags and the ISMs they hold.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint
from sogm_service.store.s3 import S3Store
from sogm_service.wire.keys import MapKeys
from sogm_service.wire.tilefile import marks_of
from tests.conftest import ServerProcess, start_server, wait_until
from tests.integration.test_cluster_answers_are_complete import (
    N_ISMS,
    RES,
    deterministic_isms,
    member_stats,
    served_tiles,
    window,
)
from tests.s3server import BUCKET

pytestmark = [pytest.mark.integration, pytest.mark.slow]
KEY = "ism/r1/laser/obstacle"


@pytest.fixture
def bucket(seaweedfs: Any, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """A fresh prefix of the test bucket, and the AWS environment the servers inherit."""
    for name, value in seaweedfs.env.items():
        monkeypatch.setenv(name, value)
    return {"url": f"s3://{BUCKET}/{seaweedfs.new_prefix()}/site",
            "endpoint_url": seaweedfs.endpoint_url}


def s3_member(tmp_path: Path, name: str, router: str, servers: int, bucket: dict[str, Any],
              checkpoint_s: float = 0.5) -> ServerProcess:
    """A member with no disk of its own: its tiles are the bucket's."""
    (tmp_path / name).mkdir(exist_ok=True)
    return start_server(tmp_path / name, {
        "cluster": {"enabled": True, "replicas": 2, "fetch_timeout_s": 5.0},
        "storage": {"checkpoint_interval_s": checkpoint_s},
        "store": bucket,
        "zenoh": {"listen": [free_tcp_endpoint()], "connect": [router]},
    }, name=name, servers=servers, wait=60.0)


def publish(robot: MapClient, first_stamp: float, seed: int) -> None:
    for k, (grid, origin) in enumerate(deterministic_isms(seed=seed)):
        robot.publish_ism(KEY, grid, resolution=RES, origin=origin, stamp=first_stamp + k)


def fused_and_written(robot: MapClient, members: int, n: int) -> bool:
    """Every member has taken ``n`` ISMs (fused or not its tiles') and written every tile."""
    stats = member_stats(robot)
    return len(stats) == members and all(
        s["counters"].get("isms_fused", 0) + s["counters"].get("cluster_isms_elsewhere", 0)
        >= n and not s["extra"].get("cluster_handover") and s["extra"].get("dirty_tiles") == 0
        and s["extra"].get("writes_pending") == 0 for s in stats.values())


def stored_marks(bucket: dict[str, Any]) -> dict[tuple[int, int], dict[str, Any]]:
    store = S3Store(bucket["url"], "default", 0.05, 256, frame=None, readonly=True,
                    endpoint_url=bucket["endpoint_url"])
    return {index: marks_of(info.header) for index, info in store.index().items()}


@pytest.mark.timeout(300)
def test_a_whole_cluster_restarted_on_its_bucket_has_the_map_back(
        tmp_path: Path, router: str, bucket: dict[str, Any], procs: list[ServerProcess]) -> None:
    for k, name in enumerate("abc"):
        procs.append(s3_member(tmp_path, name, router, k + 1, bucket))
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 3, 30)
        publish(robot, 1000.0, seed=11)
        assert wait_until(lambda: fused_and_written(robot, 3, N_ISMS), 90), member_stats(robot)
        before = window(robot)
        held = set().union(*served_tiles(robot).values())
    assert np.count_nonzero(before) > 0.5 * before.size
    tiles = stored_marks(bucket)
    assert len(held) >= 40 and set(tiles) == held  # nobody deleted what it stopped owning
    for p in procs:
        p.proc.kill()
        p.proc.wait(10)
    fresh = s3_member(tmp_path, "fresh", router, 1, bucket)
    procs.append(fresh)
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 1, 30)
        assert np.array_equal(window(robot), before)


@pytest.mark.timeout(300)
def test_a_member_resumed_after_the_others_took_over_never_overwrites_a_newer_tile(
        tmp_path: Path, router: str, bucket: dict[str, Any], procs: list[ServerProcess]) -> None:
    # a never checkpoints on its own (only at shutdown): whatever it writes is its old state.
    a = s3_member(tmp_path, "a", router, 1, bucket, checkpoint_s=3600.0)
    procs.append(a)
    for k, name in enumerate("bc"):
        procs.append(s3_member(tmp_path, name, router, k + 2, bucket))
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 3, 30)
        publish(robot, 1000.0, seed=11)
        assert wait_until(lambda: all(
            s["counters"].get("isms_fused", 0) + s["counters"].get("cluster_isms_elsewhere", 0)
            >= N_ISMS for s in member_stats(robot).values()), 90)
        os.kill(a.proc.pid, signal.SIGSTOP)
        try:  # the others see a leave after Zenoh's lease (10 s) and take its tiles over;
            # a stopped member answers no stats, so wait for the view, not for two replies.
            assert wait_until(lambda: all(
                len(s["extra"]["cluster_members"]) == 2 for s in member_stats(robot).values()),
                60)
            assert wait_until(lambda: fused_and_written(robot, 2, N_ISMS), 60)
            publish(robot, 2000.0, seed=12)  # newer ISMs over the whole area
            assert wait_until(lambda: fused_and_written(robot, 2, 2 * N_ISMS), 90), \
                member_stats(robot)
            newer = stored_marks(bucket)
        finally:
            os.kill(a.proc.pid, signal.SIGCONT)
        a.proc.send_signal(signal.SIGTERM)  # shutdown flushes a's stale dirty tiles
        a.proc.wait(60)
    assert any(m.get(KEY, (0.0,))[0] >= 2000.0 for m in newer.values())
    assert stored_marks(bucket) == newer  # a overwrote no newer tile
    log = a.log()
    assert "holds ISMs this one lacks" in log, log[-3000:]


@pytest.mark.timeout(300)
def test_a_joining_member_loads_its_tiles_from_the_bucket(
        tmp_path: Path, router: str, bucket: dict[str, Any], procs: list[ServerProcess]) -> None:
    """The members never checkpoint on their own, so the bucket's copies are behind their
    memory when a third member joins: the owners write their copies to the bucket for it and
    answer ``stored``, and it loads them from there (no tile crosses Zenoh); its sub-map
    equals theirs."""
    for k, name in enumerate("ab"):
        procs.append(s3_member(tmp_path, name, router, k + 1, bucket, checkpoint_s=3600.0))
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 2, 30)
        publish(robot, 1000.0, seed=11)
        assert wait_until(lambda: all(
            s["counters"].get("isms_fused", 0) >= N_ISMS for s in member_stats(robot).values()),
            90)
        before = window(robot)
        assert stored_marks(bucket) == {}  # nothing written yet
        c = s3_member(tmp_path, "c", router, 3, bucket, checkpoint_s=3600.0)
        procs.append(c)
        assert wait_until(lambda: len(member_stats(robot)) == 3 and not any(
            s["extra"].get("cluster_handover") for s in member_stats(robot).values()), 60)
        stats = member_stats(robot)
        joiner = stats[c.server_id]["counters"]
        assert joiner.get("cluster_tiles_loaded_from_store", 0) >= 10, joiner
        assert joiner.get("cluster_tiles_pulled", 0) == 0  # none came as a blob
        assert sum(s["counters"].get("cluster_tiles_written_for_handover", 0)
                   for s in stats.values()) >= joiner["cluster_tiles_loaded_from_store"]
        keys = MapKeys(robot.prefix, robot.map_name)
        assert np.array_equal(window(robot, keys.member(c.server_id, "submap")), before)


@pytest.mark.timeout(300)
def test_tiles_whose_primary_died_unwritten_reach_the_bucket(
        tmp_path: Path, router: str, bucket: dict[str, Any], procs: list[ServerProcess]) -> None:
    """Checkpoints write a tile on its primary only.  Of two members (both own every tile, so
    nobody pulls a tile when one leaves), a never checkpoints and is killed: b, primary of
    a's tiles now, writes them, so after b is killed too a fresh member has the whole map."""
    a = s3_member(tmp_path, "a", router, 1, bucket, checkpoint_s=3600.0)
    procs.append(a)
    procs.append(s3_member(tmp_path, "b", router, 2, bucket))
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 2, 30)
        publish(robot, 1000.0, seed=11)
        assert wait_until(lambda: all(
            s["counters"].get("isms_fused", 0) + s["counters"].get("cluster_isms_elsewhere", 0)
            >= N_ISMS for s in member_stats(robot).values()), 90)
        before = window(robot)
        a.proc.kill()
        a.proc.wait(10)
        assert wait_until(lambda: all(  # b has seen a leave
            len(s["extra"]["cluster_members"]) == 1 for s in member_stats(robot).values()), 60)
        assert wait_until(lambda: fused_and_written(robot, 1, N_ISMS), 60), member_stats(robot)
    for p in procs:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(10)
    procs.append(s3_member(tmp_path, "fresh", router, 1, bucket))
    with MapClient.connect(router, timeout=5.0) as robot:
        assert wait_until(lambda: len(member_stats(robot)) == 1, 30)
        assert np.array_equal(window(robot), before)
