"""A bounded per-connection queue of messages for one browser: drop-oldest, never blocks.

Whatever a browser does (a slow link, a hidden tab, a stuck socket), putting a message never
waits and the queue never holds more than ``capacity`` messages: when it is full the oldest
*droppable* message (a tile, a pose, a stats sample) is dropped, or the oldest of all when every
message is a control message.  A dropped tile is not lost for good: the tile's ``on_drop`` lets
the connection forget it so that the next refresh sends it again.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(slots=True)
class Message:
    """A text (JSON) or binary WebSocket message, and what to do once it is sent or dropped."""

    data: str | bytes
    droppable: bool = True
    kind: str = ""
    on_sent: Callable[[], None] | None = None
    on_drop: Callable[[], None] | None = None


@dataclass
class Outbox:
    capacity: int = 256
    dropped: int = 0
    _items: deque[Message] = field(default_factory=deque)
    _ready: asyncio.Event = field(default_factory=asyncio.Event)
    _closed: bool = False

    def __len__(self) -> int:
        return len(self._items)

    def count(self, kind: str) -> int:
        return sum(1 for m in self._items if m.kind == kind)

    def put(self, msg: Message) -> None:
        """Enqueue without waiting; drops the oldest droppable message when full."""
        if self._closed:
            return
        while len(self._items) >= self.capacity:
            victim = next((m for m in self._items if m.droppable), self._items[0])
            self._items.remove(victim)
            self.dropped += 1
            if victim.on_drop is not None:
                victim.on_drop()
        self._items.append(msg)
        self._ready.set()

    async def get(self) -> Message | None:
        """The next message, or ``None`` once closed."""
        while not self._items:
            if self._closed:
                return None
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()

    def close(self) -> None:
        self._closed = True
        for msg in self._items:
            if msg.on_drop is not None:
                msg.on_drop()
        self._items.clear()
        self._ready.set()
