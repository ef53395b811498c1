"""Through a real server and a plain Zenoh session: query parameters are typed strictly, as
ISMs are.  A body's ``true`` or ``"2"`` is no width, a parameter given twice (in the selector
or in the body) is refused with ``bad_parameter`` naming it, counted, and changes nothing."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh

from sogm_service.core.geometry import Pose2D
from tests.conftest import ServerProcess, start_server, wait_processed, wait_until
from tests.helpers import raw_session

pytestmark = pytest.mark.integration

WINDOWS = ("submap", "fused", "supercells")
# a msgpack map of two entries, both "width": what no msgpack library writes from a dict
REPEATED_BODY = b"\x82\xa5width\x01\xa5width\x02"


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    server = start_server(tmp_path_factory.mktemp("strict"), {"map": {"resolution": 0.1}})
    with server.client() as c:
        c.publish_ism("ism/robot1/laser/obstacle", np.full((20, 20), 200, dtype=np.uint8),
                      resolution=0.1, origin=Pose2D(-1.0, -1.0, 0.0))
        assert wait_processed(c, 1).get("isms_fused") == 1
    yield server
    server.terminate()


@pytest.fixture(scope="module")
def session(srv: ServerProcess) -> Iterator[zenoh.Session]:
    s = raw_session(srv.endpoint)
    yield s
    s.close()


def _ask(session: zenoh.Session, selector: str, body: bytes | None = None) -> dict[str, Any]:
    """The one reply's map, with ``ok`` telling whether it is an answer or a refusal."""
    (reply,) = list(session.get(selector, payload=body, timeout=10.0))
    if reply.ok is not None:
        return {"ok": True}
    assert reply.err is not None
    return {"ok": False, **msgpack.unpackb(reply.err.payload.to_bytes())}


def _counter(session: zenoh.Session, name: str) -> int:
    (reply,) = list(session.get("sogm/default/stats", timeout=10.0))
    assert reply.ok is not None
    return int(msgpack.unpackb(reply.ok.payload.to_bytes())["counters"].get(name, 0))


def _map_bytes(session: zenoh.Session) -> bytes:
    (reply,) = list(session.get("sogm/default/submap?width=2;height=2;encoding=logodds_i16",
                                timeout=10.0))
    assert reply.ok is not None
    return bytes(msgpack.unpackb(reply.ok.payload.to_bytes())["data"]["data"])


@pytest.mark.parametrize("what", WINDOWS)
@pytest.mark.parametrize(("body", "parameter"), [
    ({"width": True}, "width"),  # a boolean is no number
    ({"width": "2"}, "width"),  # a string is no number in a body
    ({"x": False}, "x"),
    ({"resolution": True}, "resolution"),
    ({"layers": [1]}, "layers.0"),
    ({"layers": ["robot1 laser"]}, "layers.0"),  # no layer name nor pattern
])
def test_a_loosely_typed_body_is_refused(session: zenoh.Session, what: str,
                                         body: dict[str, Any], parameter: str) -> None:
    got = _ask(session, f"sogm/default/{what}", msgpack.packb(body))
    assert (got["ok"], got.get("code"), got.get("parameter")) == (False, "bad_parameter",
                                                                  parameter)


@pytest.mark.parametrize(("body", "parameter"), [
    ({"block_size": 8.0}, "block_size"),  # a float is no integer
    ({"block_size": True}, "block_size"),
    ({"labels": 1}, "labels"),  # a number is no boolean
])
def test_supercell_parameters_are_typed_strictly(session: zenoh.Session,
                                                 body: dict[str, Any], parameter: str) -> None:
    got = _ask(session, "sogm/default/supercells", msgpack.packb(body))
    assert (got["ok"], got.get("code"), got.get("parameter")) == (False, "bad_parameter",
                                                                  parameter)


@pytest.mark.parametrize("what", WINDOWS)
def test_a_parameter_given_twice_is_refused(session: zenoh.Session, what: str) -> None:
    before = _counter(session, "query_errors_bad_parameter")
    in_selector = _ask(session, f"sogm/default/{what}?width=1;width=2")
    in_body = _ask(session, f"sogm/default/{what}", REPEATED_BODY)
    for got in (in_selector, in_body):
        assert (got["ok"], got["code"], got["parameter"]) == (False, "bad_parameter", "width")
        assert "more than once" in got["message"]
    assert _counter(session, "query_errors_bad_parameter") == before + 2


def test_tiles_changed_refuses_a_repeat_too(session: zenoh.Session) -> None:
    def changed(selector: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        (reply,) = list(session.get(selector, timeout=10.0,
                                    payload=None if body is None else msgpack.packb(body),
                                    accept_replies=zenoh.ReplyKeyExpr.ANY))
        assert reply.err is not None
        return dict(msgpack.unpackb(reply.err.payload.to_bytes()))

    key = "sogm/default/tiles/changed"
    for got, parameter in ((changed(key + "?i0=0;j0=0;i1=0;j1=0;i1=1"), "i1"),
                           (changed(key, {"i0": 0, "j0": 0, "i1": 0, "j1": True}), "j1"),
                           (changed(key + "?i0=0", {"i0": 0, "j0": 0, "i1": 0, "j1": 0}),
                            "i0")):
        assert (got["code"], got["parameter"]) == ("bad_parameter", parameter)


def test_well_typed_parameters_still_answer(session: zenoh.Session) -> None:
    """Selector strings are parsed as the field's type, a body's numbers are numbers (an
    integer is a number of metres); the selector and the body together name each parameter
    once."""
    assert _ask(session, "sogm/default/submap?width=2.5;height=2;labels_unused=1")["code"] \
        == "bad_parameter"  # unknown parameters stay refused
    assert _ask(session, "sogm/default/submap?width=2.5;height=2")["ok"]
    assert _ask(session, "sogm/default/fused", msgpack.packb({"width": 2, "height": 2.0}))["ok"]
    assert _ask(session, "sogm/default/submap?width=2",
                msgpack.packb({"height": 1, "layers": ["*/laser/*"]}))["ok"]
    got = _ask(session, "sogm/default/submap?width=2", msgpack.packb({"width": 2}))
    assert (got["code"], got["parameter"]) == ("bad_parameter", "width")


def test_refusals_change_nothing_and_log_short_lines(srv: ServerProcess,
                                                     session: zenoh.Session) -> None:
    before = _map_bytes(session)
    time.sleep(1.1)  # past the last second's line of this code (earlier tests refused too)
    lines_before = _refusal_lines(srv)
    started = time.monotonic()
    for _ in range(20):
        _ask(session, "sogm/default/submap?width=1;width=2")
        _ask(session, "sogm/default/fused", REPEATED_BODY)
        _ask(session, "sogm/default/submap", msgpack.packb({"width": True, "layers": ["*"]}))
        _ask(session, "sogm/default/submap", msgpack.packb({"layers": ["x" * 100_000]}))
    elapsed = time.monotonic() - started
    assert _map_bytes(session) == before
    assert _counter(session, "query_errors_internal") == 0
    assert wait_until(lambda: len(_refusal_lines(srv)) > len(lines_before), timeout=5.0)
    new = _refusal_lines(srv)[len(lines_before):]
    assert 1 <= len(new) <= elapsed + 2  # at most one a second per code: 80 refusals here
    assert all(len(line) < 400 for line in new)


def _refusal_lines(srv: ServerProcess) -> list[str]:
    return [ln for ln in srv.log().splitlines() if "refused query [bad_parameter]" in ln]
