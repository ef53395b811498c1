"""A server offered more ISMs than it can fuse pushes back (lossless) and keeps answering
queries: its Zenoh receive runtime has the threads ``[limits] rx_threads`` asks, so the links
held by the push-back leave others to receive queries, and every ISM published is fused or
counted by reason."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from sogm_service.bench.compute import MAP_RES, synthetic_ism
from sogm_service.core.geometry import Pose2D
from tests.conftest import start_server, wait_until

pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(not Path("/proc/self/task").exists(),
                                 reason="thread names from /proc")]

LAYERS = ["flood/layer0", "flood/layer1"]


def _rx_threads(pid: int) -> int:
    names = [(t / "comm").read_text().strip() for t in Path(f"/proc/{pid}/task").iterdir()]
    return sum(1 for n in names if n.startswith("rx-"))


def test_the_receive_runtime_has_the_configured_threads(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    old = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)  # the child inherits no runtime setting of this process
    try:
        srv = start_server(tmp_path, {"limits": {"rx_threads": 5}})
    finally:
        os.environ.clear()
        os.environ.update(old)
    try:
        with srv.client():  # a link in: the runtime is running
            assert wait_until(lambda: _rx_threads(srv.proc.pid) == 5, 10.0), \
                _rx_threads(srv.proc.pid)
    finally:
        srv.terminate()


def _flooder(endpoint: str, seed: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "sogm_service.bench.procs", "flood", "--connect", endpoint,
         "--size", "128", "--seed", str(seed), "--layers", ",".join(LAYERS)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def _line(proc: subprocess.Popen[str], word: str) -> list[str]:
    assert proc.stdout is not None
    while True:
        parts = proc.stdout.readline().split()
        if not parts:
            raise RuntimeError(f"flood publisher ended before {word!r}")
        if parts[0] == word:
            return parts[1:]


@pytest.mark.parametrize("policy", ["lossless", "latest"])
def test_a_flood_is_pushed_back_or_shed_accounted_for_and_queries_answered(
        tmp_path: Path, policy: str) -> None:
    """``lossless`` pushes back (callbacks wait for room); ``latest`` sheds what a newer ISM
    of its key replaced, counted: either way fused + counted = published."""
    srv = start_server(tmp_path, {"map": {"resolution": MAP_RES},
                                  "limits": {"queue_size": 4, "queue_policy": policy}})
    floods: list[subprocess.Popen[str]] = []
    try:
        with srv.client(timeout=30.0) as client:
            for k, layer in enumerate(LAYERS):
                client.publish_ism(f"ism/fill/{layer}", synthetic_ism(512, k),
                                   resolution=MAP_RES, origin=Pose2D(0.0, 0.0, 0.0),
                                   layer=layer, wait=True, timeout=30.0)
            floods = [_flooder(srv.endpoint, k) for k in range(2)]
            for f in floods:
                _line(f, "ready")
            before = client.stats().counters
            sent: list[int] = []

            def flood() -> None:
                for f in floods:
                    assert f.stdin is not None
                    f.stdin.write("3\n")
                    f.stdin.flush()
                sent.extend(int(_line(f, "sent")[0]) for f in floods)

            thread = threading.Thread(target=flood)
            thread.start()
            answered_during = 0
            while thread.is_alive():
                client.submap(x=6.4, y=6.4, yaw=0.5, width=12.8, height=12.8,
                              resolution=MAP_RES, layers=LAYERS)
                answered_during += thread.is_alive()
            thread.join()
            published = sum(sent)

            def handled() -> dict[str, int]:
                c = client.stats().counters
                return {k: c.get(k, 0) - before.get(k, 0) for k in
                        ("isms_fused", "isms_rejected", "isms_dropped_latest", "isms_received",
                         "isms_pushed_back")}

            assert wait_until(lambda: handled()["isms_fused"] + handled()["isms_rejected"]
                              + handled()["isms_dropped_latest"] >= published, 120.0, 0.2), \
                (handled(), published)
            counts = handled()
        if policy == "lossless":  # offered more than it fuses: the publishers were held
            assert counts["isms_pushed_back"] > 0 and counts["isms_dropped_latest"] == 0, counts
        else:  # ... or the superseded ISMs were shed
            assert counts["isms_dropped_latest"] > 0 and counts["isms_pushed_back"] == 0, counts
        assert counts["isms_received"] == published
        assert counts["isms_fused"] + counts["isms_rejected"] + counts["isms_dropped_latest"] \
            == published, (counts, published)
        assert answered_during >= 3, "sub-maps were not answered while the flood ran"
    finally:
        for f in floods:
            if f.stdin is not None:
                f.stdin.close()
            f.wait(30)
        srv.terminate()
