"""Service errors on the wire (wire/errors): a busy refusal travels with its retry hint; older
error replies still decode."""

from __future__ import annotations

import msgpack

from sogm_service.wire import codec
from sogm_service.wire.messages import ErrorReply


def test_busy_travels_with_its_hint_and_old_error_replies_still_decode() -> None:
    from sogm_service.client.results import service_error

    exc = service_error(codec.encode(ErrorReply(code="busy", message="m", retry_after_s=0.5)))
    assert exc.code == "busy" and exc.retry_after_s == 0.5
    old = msgpack.packb({"code": "window_too_large", "message": "m", "parameter": "width"})
    exc = service_error(old)  # a reply of a server before the field: no hint
    assert exc.code == "window_too_large" and exc.retry_after_s is None
