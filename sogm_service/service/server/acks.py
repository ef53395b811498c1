"""Publishers hear back: what became of each ISM (fused, or rejected and why).

Two channels, both fed by :class:`~sogm_service.service.server.pipeline.IngestPipeline` through
:meth:`IsmOutcomes.outcome`:

* **Rejection reports**: every rejected ISM is published as a
  :class:`~sogm_service.wire.messages.RejectionReport` on ``<prefix>/<map>/rejections/<robot>``
  (the robot chunk of the ISM's key; ``_unknown`` when the key has none), whether or not its
  publisher asked for anything, so a robot (or an operator) can subscribe to its own refusals.
* **Acknowledgements**: an ISM published with an id (its Zenoh attachment, UTF-8,
  :data:`~sogm_service.wire.limits.ISM_ID_PATTERN`) is remembered from the moment it is received
  (``queued``) until it is ``fused`` (its cells are in the tiles: a query sees them) or
  ``rejected``; the queryable ``<prefix>/<map>/ack?id=<id>`` answers an
  :class:`~sogm_service.wire.messages.IsmAck`.  The table is bounded (the oldest outcomes go
  first), never blocks a query thread, and costs nothing for ISMs without an id.

Why a queryable rather than only a publication: the client asks when it wants to know, so an
answer cannot be lost to a subscriber declared late, a router in between or a reconnect, and a
busy server (a deep queue) is simply ``queued`` for longer.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from sogm_service.wire import codec
from sogm_service.wire.keys import MapKeys, is_key_chunk, robot_of_ism_key
from sogm_service.wire.limits import ACK_TABLE_SIZE, ISM_ID_PATTERN, REJECTION_MESSAGE_CHARS
from sogm_service.wire.messages import IsmAck, RejectionReport

_ISM_ID = re.compile(ISM_ID_PATTERN)


def ism_id_of(attachment: bytes | None) -> str | None:
    """The ISM id an attachment carries, or ``None`` (absent or not a valid id: ignored)."""
    if not attachment or len(attachment) > 64:
        return None
    try:
        text = attachment.decode("ascii")
    except UnicodeDecodeError:
        return None
    return text if _ISM_ID.match(text) else None


class IsmOutcomes:
    """The bounded table of acknowledged ISMs and the rejection publisher."""

    def __init__(self, keys: MapKeys, key_exprs: list[str],
                 put: Callable[[str, bytes], None] | None = None,
                 capacity: int = ACK_TABLE_SIZE) -> None:
        self._keys = keys
        self._key_exprs = key_exprs
        self._put = put
        self._capacity = capacity
        self._lock = threading.Lock()
        self._table: OrderedDict[str, IsmAck] = OrderedDict()

    def attach(self, put: Callable[[str, bytes], None] | None) -> None:
        """Where rejection reports go (``session.put``); ``None`` stops them."""
        self._put = put

    def queued(self, ism_id: str | None, key: str) -> None:
        if ism_id is not None:
            self._store(IsmAck(id=ism_id, status="queued", key=key, stamp=time.time()))

    def outcome(self, key: str, source: int, ism_id: str | None, code: str | None,
                message: str) -> None:
        """An ISM is fused (``code`` None) or rejected with ``code``: remember it when it has
        an id, and publish every rejection for its robot."""
        now = time.time()
        text = message[:REJECTION_MESSAGE_CHARS]
        if ism_id is not None:
            self._store(IsmAck(id=ism_id, status="fused" if code is None else "rejected",
                               key=key, code=code, message=text, stamp=now))
        if code is not None and self._put is not None:
            report = RejectionReport(key=key[:256], code=code, message=text, stamp=now,
                                     id=ism_id)
            # A closing session may refuse: the counter and the log still have it.
            with contextlib.suppress(Exception):
                self._put(self._keys.rejections(self.robot_of(key, source)),
                          codec.encode(report))

    def lookup(self, ism_id: str) -> IsmAck:
        with self._lock:
            ack = self._table.get(ism_id)
        return ack if ack is not None else IsmAck(id=ism_id, status="unknown")

    def robot_of(self, key: str, source: int) -> str:
        expr = self._key_exprs[source] if 0 <= source < len(self._key_exprs) else ""
        robot = robot_of_ism_key(key, expr) if expr else ""
        return robot if is_key_chunk(robot) else "_unknown"

    def _store(self, ack: IsmAck) -> None:
        with self._lock:
            self._table[ack.id] = ack
            self._table.move_to_end(ack.id)
            while len(self._table) > self._capacity:
                self._table.popitem(last=False)
