"""Sample attachments of rmw_zenoh (adapters/ros2/attachment): sequence number, time stamp
and publisher gid, in the current and the keyed (Humble) form.

The expected values here are literal strings from rmw_zenoh's wire as documented by the
rmw_zenoh project, or built by hand from its byte layout (struct, xxhash, zenoh-ext's own
serializer) and with rosbags, never with the adapter's encoders.
"""

from __future__ import annotations

import struct

import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
xxhash = pytest.importorskip("xxhash")

import zenoh.ext  # noqa: E402  (the zenoh-ext serializer as an independent reference)

from sogm_service.adapters.ros2 import Ros2DecodeError  # noqa: E402
from sogm_service.adapters.ros2.attachment import gid_of, parse_attachment  # noqa: E402


def _spec_gid(key: str) -> bytes:
    h = xxhash.xxh3_128(key.encode())
    lo, hi = h.intdigest() & (2**64 - 1), h.intdigest() >> 64
    return struct.pack("<QQ", lo, hi)  # "low 64 bits first"


def test_attachment_current_form_built_by_hand_and_by_zenoh_ext() -> None:
    token = "@ros2_lv/0/aa/0/3/MP/%/%/n/%ism%r%a/nav_msgs::msg::dds_::OccupancyGrid_/h/::,10:,:,:,,"
    gid = _spec_gid(token)
    assert gid_of(token) == gid
    by_hand = struct.pack("<qqB", 1, 1_700_000_000_123_456_789, 16) + gid
    assert len(by_hand) == 33
    ts_ns = zenoh.ext.Int64(1_700_000_000_123_456_789)
    by_zenoh = zenoh.ext.z_serialize((zenoh.ext.Int64(1), ts_ns, gid)).to_bytes()
    assert by_zenoh == by_hand
    att = parse_attachment(by_hand)
    assert (att.sequence_number, att.source_timestamp_ns, att.gid) == \
        (1, 1_700_000_000_123_456_789, gid)


def test_attachment_keyed_form_and_humble_gid() -> None:
    gid = bytes(range(16))
    keyed = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(42), "source_timestamp",
                                   zenoh.ext.Int64(99), "source_gid", gid)).to_bytes()
    assert keyed[0] == 15 and keyed[1:16] == b"sequence_number"
    att = parse_attachment(keyed)
    assert (att.sequence_number, att.source_timestamp_ns, att.gid) == (42, 99, gid)
    humble = struct.pack("<qqB", 3, 4, 24) + bytes(24)
    assert parse_attachment(humble).gid == bytes(24)


@pytest.mark.parametrize("bad", [
    None, b"", b"\x01" * 16, struct.pack("<qqB", 1, 2, 16) + bytes(15),
    struct.pack("<qqB", 1, 2, 16) + bytes(17), struct.pack("<qqB", 1, 2, 8) + bytes(8),
    b"\x0fsequence_number" + bytes(3), struct.pack("<qqB", -1, 2, 16) + bytes(16),
    b"\xff" * 300,
])
def test_bad_attachments_are_refused_with_their_code(bad: bytes | None) -> None:
    with pytest.raises(Ros2DecodeError) as e:
        parse_attachment(bad)
    assert e.value.code == "bad_attachment"
    assert e.value.parameter is None
