"""Every payload the server sends declares its encoding, read here by a plain Zenoh session (no
project client): msgpack wire models as ``application/msgpack`` (replies, error replies, tile
events, rejection reports, and the client's ISMs and poses), whole tiles as
``application/x-sogm-tile``.  Without a declared
encoding a generic Zenoh tool sees ``zenoh/bytes`` and cannot tell what it holds."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from tests.conftest import ServerProcess, wait_until
from tests.helpers import raw_session

pytestmark = pytest.mark.integration

MSGPACK = "application/msgpack"
TILE = "application/x-sogm-tile"




def _replies(session: zenoh.Session, selector: str) -> list[zenoh.Reply]:
    return list(session.get(selector, timeout=10.0))


def test_replies_errors_events_and_tiles_declare_their_encoding(server: ServerProcess) -> None:
    events: list[zenoh.Sample] = []
    rejections: list[zenoh.Sample] = []
    sent: list[zenoh.Sample] = []  # what the client puts: ISMs and poses
    lock = threading.Lock()

    def keep(into: list[zenoh.Sample]) -> object:
        def on_sample(sample: zenoh.Sample) -> None:
            with lock:
                into.append(sample)
        return on_sample

    raw = raw_session(server.endpoint)
    try:
        subs = [raw.declare_subscriber("sogm/default/events/tile", keep(events)),
                raw.declare_subscriber("sogm/default/rejections/**", keep(rejections)),
                raw.declare_subscriber("ism/robot1/**", keep(sent)),
                raw.declare_subscriber("pose/**", keep(sent))]
        with server.client() as client:
            client.publish_ism("ism/robot1/laser/obstacle", np.full((40, 40), 230, np.uint8),
                               resolution=0.05, robot="robot1", wait=True)
            client.publish_pose("robot1", x=1.0, y=1.0)
            client.publish_pose("robot1", x=40.0, y=1.0)  # three tiles on: a tile switch
            client.publish_raw("ism/robot2/laser/obstacle", b"\xc1 not msgpack")

            for name in ("submap?x=1;y=1;width=2;height=2;resolution=0.1", "fused?x=1;y=1;"
                         "width=2;height=2;resolution=0.1", "info", "stats", "robots"):
                (reply,) = _replies(raw, f"sogm/default/{name}")
                assert reply.ok is not None, name
                assert str(reply.ok.encoding) == MSGPACK, name
                assert isinstance(msgpack.unpackb(reply.ok.payload.to_bytes()), dict)

            (refused,) = _replies(raw, "sogm/default/submap?x=1;y=1;width=-2;height=2")
            assert refused.err is not None
            assert str(refused.err.encoding) == MSGPACK
            assert msgpack.unpackb(refused.err.payload.to_bytes())["code"] == "bad_parameter"

            tiles = _replies(raw, "sogm/default/tiles/**")
            assert tiles and all(r.ok is not None for r in tiles)
            assert {str(r.ok.encoding) for r in tiles if r.ok is not None} == {TILE}

            assert wait_until(lambda: bool(events) and bool(rejections) and len(sent) >= 3,
                              timeout=10.0)
        with lock:
            assert {str(s.encoding) for s in events} == {MSGPACK}
            assert {str(s.encoding) for s in rejections} == {MSGPACK}
            assert {str(s.encoding) for s in sent} == {MSGPACK}
            assert msgpack.unpackb(rejections[0].payload.to_bytes())["code"] \
                == "malformed_msgpack"
        for sub in subs:
            sub.undeclare()
    finally:
        raw.close()


def test_the_docs_example_reads_a_reply_with_zenoh_and_msgpack_alone(
        server: ServerProcess) -> None:
    """The wire page's example, run as it is written (only the endpoint is this server's)."""
    page = (Path(__file__).resolve().parents[2] / "docs" / "wire.md").read_text()
    section = page.split("## Reading a reply with a generic Zenoh tool", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S)
    assert code is not None
    script = code.group(1).replace("tcp/127.0.0.1:7447", server.endpoint)
    assert "sogm_service" not in script
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert out.splitlines()[0] == MSGPACK
    assert "'map': 'default'" in out
