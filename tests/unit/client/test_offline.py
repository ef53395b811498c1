"""The offline buffer: the latest ISM per key kept, every other one dropped and counted."""

from __future__ import annotations

import pytest

from sogm_service.client.offline import HeldIsm, OfflineBuffer


def item(key: str, n: int, size: int = 10) -> HeldIsm:
    return HeldIsm(key, bytes(size), f"id-{n}")


def test_only_the_latest_of_a_key_is_kept_and_the_rest_counted() -> None:
    buf = OfflineBuffer()
    dropped: list[str] = []
    for n in range(5):
        buf.offered()
        dropped += buf.hold(item("ism/r1/laser/obstacle", n))
    buf.offered()
    dropped += buf.hold(item("ism/r1/camera/floor", 9))
    assert dropped == ["id-0", "id-1", "id-2", "id-3"]
    stats = buf.stats()
    assert (stats.offered, stats.held, stats.dropped_superseded, stats.dropped) == (6, 2, 4, 4)
    assert [i.ism_id for i in buf.take()] == ["id-4", "id-9"]  # oldest first
    assert len(buf) == 0


def test_the_buffer_is_bounded_in_keys_and_bytes() -> None:
    buf = OfflineBuffer(max_keys=2, max_bytes=25)
    assert buf.hold(item("a", 1)) == []
    assert buf.hold(item("b", 2)) == []
    assert buf.hold(item("c", 3)) == ["id-1"]  # a third key evicts the oldest
    assert buf.hold(item("d", 4, size=20)) == ["id-2", "id-3"]  # 20 + 10 bytes > 25
    assert buf.hold(item("e", 5, size=26)) == ["id-4", "id-5"]  # larger than the buffer
    stats = buf.stats()
    assert (stats.held, stats.dropped_overflow) == (0, 5)
    with pytest.raises(ValueError):
        OfflineBuffer(max_keys=0)


def test_put_back_keeps_order_and_yields_to_a_newer_ism() -> None:
    buf = OfflineBuffer()
    buf.hold(item("a", 1))
    buf.hold(item("b", 2))
    taken = buf.take()
    buf.hold(item("b", 3))  # arrived while the first two were out
    assert buf.put_back(taken) == ["id-2"]
    assert [i.ism_id for i in buf.take()] == ["id-1", "id-3"]
    assert buf.stats().dropped_superseded == 1


def test_an_outage_is_counted_once_per_lost_route_and_discard_counts_unsent() -> None:
    buf = OfflineBuffer()
    buf.sent("a")
    buf.hold(item("a", 1))
    buf.hold(item("a", 2))
    assert buf.stats().outages == 1
    assert buf.discard() == ["id-2"]
    stats = buf.stats()
    assert (stats.dropped_unsent, stats.dropped, stats.held) == (1, 2, 0)
