"""The ingestion queue's push-back and the Zenoh receive runtime the server asks for."""

from __future__ import annotations

import os
import threading

import pytest

from sogm_service.service.server import ingest
from sogm_service.service.server.ingest import IngestQueue, reserve_rx_threads
from sogm_service.service.server.pipeline import IsmItem
from sogm_service.service.server.stats import Stats


def test_a_full_lossless_queue_makes_callbacks_wait_and_counts_them() -> None:
    stats = Stats()
    q = IngestQueue(1, "lossless", stats)
    assert q.put(IsmItem(0, "ism/a", b"1"))
    started = [threading.Event() for _ in range(2)]
    done: list[bool] = []

    def put(k: int) -> None:
        started[k].set()
        done.append(q.put(IsmItem(0, f"ism/{k}", b"x")))

    threads = [threading.Thread(target=put, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for e in started:
        e.wait(5)
    while q.waiting_max < 2 and all(t.is_alive() for t in threads):
        threading.Event().wait(0.01)  # both are waiting on the full queue
    assert q.waiting_max == 2 and not done
    for _ in range(3):
        assert q.get(timeout=5) is not None
    for t in threads:
        t.join(5)
    assert done == [True, True]
    assert stats.snapshot()[0]["isms_pushed_back"] == 2
    assert q.depth() == 0


def test_a_waiting_callback_is_let_in_once_half_the_queue_is_taken() -> None:
    """Not one ISM at a time: a busy server's queue is full all the time, and waking a
    callback for every ISM taken costs a thread switch per ISM."""
    q = IngestQueue(8, "lossless", Stats())
    for k in range(8):
        assert q.put(IsmItem(0, f"ism/{k}", b"x"))
    put = threading.Thread(target=q.put, args=(IsmItem(0, "ism/late", b"x"),))
    put.start()
    while q.waiting_max < 1:
        threading.Event().wait(0.01)
    for taken in range(1, 5):
        assert q.get(timeout=5) is not None
        put.join(0.3 if taken < 4 else 5)
        # still waiting until the worker has taken half (8 - 4 = 4 left), then in at once
        assert put.is_alive() == (taken < 4), taken
    assert q.depth() == 5
    keys = [item.key for item in iter(lambda: q.get(timeout=0.1), None)]
    assert keys == ["ism/4", "ism/5", "ism/6", "ism/7", "ism/late"]  # arrival order kept


def test_a_queue_with_room_counts_no_push_back() -> None:
    stats = Stats()
    q = IngestQueue(4, "lossless", stats)
    for k in range(4):
        assert q.put(IsmItem(0, f"ism/{k}", b"x"))
    assert q.waiting_max == 0 and "isms_pushed_back" not in stats.snapshot()[0]


def test_rx_threads_go_to_zenoh_unless_the_environment_says(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ingest.RUNTIME_ENV, "")  # restored (or removed) after the test
    monkeypatch.delenv(ingest.RUNTIME_ENV)
    with reserve_rx_threads(12) as set_here:  # the first session opens here
        assert set_here
        assert os.environ[ingest.RUNTIME_ENV] == "(rx: (worker_threads: 12))"
    assert ingest.RUNTIME_ENV not in os.environ  # children do not inherit it
    monkeypatch.setenv(ingest.RUNTIME_ENV, "(rx: (worker_threads: 3))")
    with reserve_rx_threads(12) as set_here:
        assert not set_here
        assert os.environ[ingest.RUNTIME_ENV] == "(rx: (worker_threads: 3))"
    assert os.environ[ingest.RUNTIME_ENV] == "(rx: (worker_threads: 3))"
