"""The rmw_zenoh attachment of every sample, query and reply (pure, no zenoh import).

Current form (Jazzy >= 0.2.4, Humble >= 0.1.2, Kilted, Rolling >= 0.6.0): the zenoh-ext
serialisation of ``(int64 sequence_number, int64 source_timestamp_ns, uint8[16] gid)``::

    offset 0   int64 LE  sequence number (per publisher, the first is 1)
    offset 8   int64 LE  source timestamp, ns since the UNIX epoch
    offset 16  0x10      LEB128 length of the gid
    offset 17  16 bytes  gid: XXH3-128 of the entity's liveliness key, low 64 bits first

33 bytes.  Older releases wrote a *keyed* form, each field preceded by its name as a zenoh-ext
string (LEB128 length + UTF-8): ``"sequence_number", seq, "source_timestamp", ts,
"source_gid", gid``.  :func:`parse_attachment` reads both; Humble's 24-byte gid
(``RMW_GID_STORAGE_SIZE`` there) is accepted as well.  Anything else is refused with
``bad_attachment``: rmw_zenoh's own subscribers drop samples without a valid attachment.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import xxhash

from sogm_service.adapters.ros2.errors import Ros2DecodeError

GID_SIZE = 16
_GID_SIZES = (16, 24)
_HEAD = struct.Struct("<qq")
_I64 = struct.Struct("<q")
_KEYS = (b"sequence_number", b"source_timestamp", b"source_gid")


@dataclass(frozen=True, slots=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        return encode_attachment(self.sequence_number, self.source_timestamp_ns, self.gid)


def gid_of(liveliness_key: str) -> bytes:
    """An entity's gid: XXH3-128 of its liveliness key, the low 64 bits first (LE)."""
    return xxhash.xxh3_128_intdigest(liveliness_key.encode("utf-8")).to_bytes(16, "little")


def encode_attachment(sequence_number: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte current form."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a gid has {GID_SIZE} bytes, got {len(gid)}")
    return _HEAD.pack(sequence_number, timestamp_ns) + bytes([GID_SIZE]) + bytes(gid)


def _leb128(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    for _ in range(5):  # lengths here are tiny; 5 bytes cover 32 bits
        if pos >= len(data):
            raise ValueError("truncated length")
        b = data[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7
    raise ValueError("length too long")


def _bytes_field(data: bytes, pos: int) -> tuple[bytes, int]:
    n, pos = _leb128(data, pos)
    if pos + n > len(data):
        raise ValueError(f"a field of {n} bytes runs past the end")
    return data[pos:pos + n], pos + n


def _int64(data: bytes, pos: int) -> tuple[int, int]:
    if pos + 8 > len(data):
        raise ValueError("truncated int64")
    return _I64.unpack_from(data, pos)[0], pos + 8


def _parse_keyed(data: bytes) -> Attachment:
    pos = _key(data, 0, _KEYS[0])
    seq, pos = _int64(data, pos)
    pos = _key(data, pos, _KEYS[1])
    ts, pos = _int64(data, pos)
    pos = _key(data, pos, _KEYS[2])
    gid, pos = _bytes_field(data, pos)
    if pos != len(data):
        raise ValueError(f"{len(data) - pos} trailing bytes")
    return Attachment(seq, ts, gid)


def _key(data: bytes, pos: int, name: bytes) -> int:
    key, pos = _bytes_field(data, pos)
    if key != name:
        raise ValueError(f"expected key {name.decode()!r}, got {key[:32]!r}")
    return pos


def _parse_current(data: bytes) -> Attachment:
    seq, ts = _HEAD.unpack_from(data, 0) if len(data) >= 16 else (0, 0)
    if len(data) < 17:
        raise ValueError(f"{len(data)} bytes, at least 17 needed")
    gid, pos = _bytes_field(data, 16)
    if pos != len(data):
        raise ValueError(f"{len(data) - pos} trailing bytes")
    return Attachment(seq, ts, gid)


def parse_attachment(data: bytes | bytearray | memoryview | None) -> Attachment:
    """Either form -> :class:`Attachment`, or ``Ros2DecodeError('bad_attachment')``."""
    if data is None:
        raise Ros2DecodeError("bad_attachment", "the sample has no attachment")
    raw = bytes(data)
    if len(raw) > 256:
        raise Ros2DecodeError("bad_attachment", f"attachment of {len(raw)} bytes is too long")
    keyed = raw[:1] == bytes([len(_KEYS[0])]) and raw[1:1 + len(_KEYS[0])] == _KEYS[0]
    try:
        att = _parse_keyed(raw) if keyed else _parse_current(raw)
    except (ValueError, struct.error) as exc:
        form = "keyed" if keyed else "current"
        raise Ros2DecodeError("bad_attachment",
                              f"attachment of {len(raw)} bytes ({form} form): {exc}") from None
    if len(att.gid) not in _GID_SIZES:
        raise Ros2DecodeError("bad_attachment", f"gid of {len(att.gid)} bytes")
    if att.sequence_number < 0:
        raise Ros2DecodeError("bad_attachment", f"negative sequence {att.sequence_number}")
    return att
