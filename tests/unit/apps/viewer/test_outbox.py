"""A browser's outbox (apps/viewer/outbox): bounded, dropping the oldest droppable message."""

from __future__ import annotations

import asyncio

from sogm_service.apps.viewer.outbox import Message, Outbox


def test_outbox_never_grows_and_drops_the_oldest_droppable_message() -> None:
    dropped: list[str] = []
    box = Outbox(capacity=3)
    box.put(Message("control", droppable=False))
    for k in range(5):
        box.put(Message(f"tile{k}", kind="tile", on_drop=lambda k=k: dropped.append(f"tile{k}")))
    assert len(box) == 3 and box.dropped == 3
    assert dropped == ["tile0", "tile1", "tile2"]

    async def take() -> list[str | bytes]:
        out = []
        for _ in range(3):
            msg = await box.get()
            assert msg is not None
            out.append(msg.data)
        return out

    assert asyncio.run(take()) == ["control", "tile3", "tile4"]
    box.close()
    assert asyncio.run(box.get()) is None


def test_a_message_that_cannot_be_json_is_dropped_not_raised() -> None:
    from sogm_service.apps.viewer.app import Connection
    from sogm_service.apps.viewer.hub import HubSettings, MapHub

    conn = Connection(None, MapHub(HubSettings()), None, 1.0, 8)  # type: ignore[arg-type]
    conn.send({"type": "stats", "isms_per_s": float("nan")})  # a server's NaN must not kill
    assert len(conn.outbox) == 0  # the ticker that pushes to every page
    conn.send({"type": "stats", "isms_per_s": 1.0})
    assert len(conn.outbox) == 1
