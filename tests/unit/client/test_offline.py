"""The offline buffer: the latest ISM per key kept, every other one dropped and counted; ISMs
the server never received go through the same rule."""

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
    buf.sent(item("a", 0))
    buf.hold(item("a", 1))
    buf.hold(item("a", 2))
    assert buf.stats().outages == 1
    assert buf.discard() == ["id-2"]
    stats = buf.stats()
    assert (stats.dropped_unsent, stats.dropped, stats.held) == (1, 2, 0)


def sent(buf: OfflineBuffer, *items: HeldIsm) -> None:
    for one in items:
        buf.offered()
        buf.sent(one)


def test_the_newest_lost_one_is_sent_again_and_older_lost_ones_dropped() -> None:
    buf = OfflineBuffer()
    sent(buf, item("a", 1), item("a", 2), item("a", 3))
    assert buf.newest() == [("a", "id-3")]
    buf.suspect("a")  # its last put is unknown to the server
    assert buf.suspects() == ["id-1", "id-2", "id-3"]
    assert buf.settled("id-1", lost=False) == []
    assert buf.settled("id-2", lost=True) == []  # id-3 not answered yet
    assert buf.settled("id-3", lost=True) == ["id-2"]  # superseded by id-3, sent again
    again = buf.take()
    assert [(i.ism_id, i.resend) for i in again] == [("id-3", True)]
    stats = buf.stats()
    assert (stats.sent, stats.dropped_superseded, stats.lost_in_flight) == (1, 1, 0)
    buf.put_back(again)
    assert buf.stats().offered == buf.stats().sent + buf.stats().held + buf.stats().dropped
    buf.sent(buf.take()[0], flushed=True)
    stats = buf.stats()
    assert (stats.offered, stats.sent, stats.flushed, stats.resent) == (3, 2, 1, 1)


def test_lost_ones_older_than_a_held_one_are_dropped_as_superseded() -> None:
    buf = OfflineBuffer()
    sent(buf, item("a", 1), item("a", 2))
    buf.offered()
    assert buf.hold(item("a", 3)) == []  # the route went: id-1 and id-2 are suspects
    assert buf.settled("id-1", lost=True) == []
    assert buf.settled("id-2", lost=True) == ["id-1", "id-2"]
    assert [(i.ism_id, i.resend) for i in buf.take()] == [("id-3", False)]
    stats = buf.stats()
    assert (stats.sent, stats.dropped_superseded, stats.outages) == (0, 2, 1)


def test_lost_ones_without_a_copy_count_as_lost_in_flight() -> None:
    buf = OfflineBuffer(max_keys=1)
    sent(buf, item("a", 1), item("b", 2))  # b's copy evicted a's: one key at most
    buf.suspect("a")
    assert buf.settled("id-1", lost=True) == []
    assert buf.take() == []
    stats = buf.stats()
    assert (stats.sent, stats.lost_in_flight, stats.dropped) == (2, 1, 0)


def test_copies_share_the_bounds_and_give_way_to_held_isms() -> None:
    buf = OfflineBuffer(max_keys=2, max_bytes=25)
    sent(buf, item("a", 1), item("b", 2))
    assert buf.hold(item("c", 3)) == []  # a copy goes, not a held ISM (nothing counted)
    assert buf.hold(item("d", 4)) == []  # the last copy goes
    assert buf.hold(item("e", 5)) == ["id-3"]  # now held ISMs: the oldest
    assert buf.stats().dropped_overflow == 1
    buf.sent(item("f", 6, size=20))  # no room beside the held ones: no copy kept
    buf.suspect("f")
    assert buf.settled("id-6", lost=True) == []
    assert buf.stats().lost_in_flight == 1
