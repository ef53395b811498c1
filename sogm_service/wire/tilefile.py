"""The tile file format: one self-describing, checksummed tile, the store's file and the wire
format of ``<prefix>/<map>/tiles/<i>/<j>`` (declared ``application/x-sogm-tile``).  Pure encoding
and validation of bytes, so that the client decodes tiles with the store's own rules; files are
read by :mod:`sogm_service.store.format` and written by :mod:`sogm_service.store.directory`.

The paper stores each tile "in binary form, tagged with kind of content, resolution, and
location" (section III-E).  File names ``sogm_<map>_r<res>_t<T>_i<+iiii>_j<+jjjj>.tile`` (e.g.
``sogm_default_r0.050_t256_i+0003_j-0012.tile``) let a person find a tile with ``ls``, and tiles
of other maps, resolutions or tile sizes share a directory without being mistaken for each other.

File format, version 1::

    offset 0   8 bytes  magic  b"SOGMTILE"
           8   u16 LE   format version (1)
          10   u16 LE   reserved (0)
          12   u32 LE   H = length of the JSON header
          16   H bytes  JSON header, UTF-8 (fields below)
        16+H   u32 LE   CRC-32 of bytes [0, 16+H)    (the header is checked before it is trusted)
        20+H   payload  zlib stream of the raw little-endian int16 array, shape (N, T, T)

JSON header fields: ``map``, ``frame``, ``i``, ``j``, ``resolution``, ``tile_size``, ``origin``
(``[x, y]`` of the tile corner in the map frame), ``layers`` (N names, in array order),
``dtype`` (``"<i2"``), ``shape``, ``scale`` (log-odds units per nat, :data:`logodds.SCALE`),
``datum`` (WGS-84 ``latitude``/``longitude``/``altitude`` of the tile origin, or null),
``stamp`` (time of the newest data in the tile), ``compression`` (``"zlib"``), ``level``,
``raw_len``, ``payload_len``, ``payload_crc32`` (CRC-32 of the compressed payload) and
``written_unix`` (wall-clock time of the write).  Optional fields, written only when non-empty
(additive within version 1: older readers ignore them, and a tile without them encodes exactly as
before they existed): ``decay`` (``{layer: decayed up to}``) and ``applied``
(``{ISM key: [stamp, digest]}``: the last ISM fused into the tile per ISM key, which a cluster's
handover compares with its journal; at most :data:`MAX_APPLIED` entries, keys of at most
:data:`MAX_APPLIED_KEY` characters, finite stamps, digests in ``[0, 2**64)``) and
``tile_version`` (an integer in ``[1, 2**63)``: the tile's version, ``Tile.version``, which
changes exactly when the tile's content does; a tile loaded back keeps it, so a client that holds
this version holds this content, :mod:`sogm_service.service.server.tilesync`).

Validation (a file failing any check is *reported* with a reason, logged, and moved into
``quarantine/`` with a ``.reason.txt`` next to it; it is never loaded and never fatal): magic,
version, header CRC, header types, file length (truncation or trailing bytes), file name agrees
with the header, map name / resolution / tile size / frame match the store, shape agrees with the
layer count and tile size, payload CRC, decompressed length, and every value within
``±logodds.MAX_STATE`` (the fusion's overflow guarantee depends on it).
"""

from __future__ import annotations

import json
import math
import struct
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.geodesy import GeoPoint, LocalTangentPlane
from sogm_service.core.map.tiletypes import LoaderResult, Mark, TileIndex, tile_token
from sogm_service.wire.errors import TileFormatError

MAGIC: Final = b"SOGMTILE"
FORMAT_VERSION: Final = 1
DEFAULT_LEVEL: Final = 1
"""zlib level.  Measured on an 8x256x256 tile (2-core machine): a noisy, 60 % observed tile
compresses 2.07x at level 1 in 15 ms vs 2.11x at level 6 in 25 ms; a saturated (clamped) tile
21.8x in 2 ms at level 1 vs 33x in 9 ms at level 6.  Decompression is 1-3 ms at any level.
A byte shuffle (high/low bytes apart) was tried and is not a clear win (2.28x noisy, 13x
saturated at level 1).  Level 1 keeps a checkpoint of many tiles cheapest in CPU."""

SUFFIX: Final = ".tile"
MapKey = tuple[str, float, int]  # one map's tiles in a store: (name, resolution, tile size)

_PREFIX = struct.Struct("<8sHHI")
_CRC = struct.Struct("<I")
_MAX_HEADER: Final = 1 << 20  # a header is a few hundred bytes; a huge length is corruption
_MAX_LAYERS: Final = 4096
_RES_TOL: Final = 1e-9
MAX_APPLIED: Final = 4096
"""Most ``applied`` marks a tile file holds (one per ISM key that wrote into the tile)."""
MAX_APPLIED_KEY: Final = 1024
"""Longest ISM key (characters) of an ``applied`` mark (a Zenoh key of prefix, map, robot and
layer: each of those is bounded far below this)."""
_DIGEST_END: Final = 1 << 64
_VERSION_END: Final = 1 << 63

Fixed = npt.NDArray[np.int16]


# -- header ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class TileHeader:
    """What a tile file says about itself (the payload fields are filled in by encoding)."""

    map_name: str
    frame: str
    i: int
    j: int
    resolution: float
    tile_size: int
    layers: tuple[str, ...]
    stamp: float
    datum: GeoPoint | None = None
    scale: float = logodds.SCALE
    version: int = FORMAT_VERSION
    written_unix: float = 0.0
    # Optional (additive in version 1): decaying layer -> the time up to which its
    # cells are decayed.  Written only when non-empty; readers before it ignore the field.
    decay: tuple[tuple[str, float], ...] = ()
    # Optional (additive in version 1): ISM key -> (stamp, digest) of the last ISM
    # fused into the tile (``Tile.applied``), sorted by key.  Written only when non-empty.
    applied: tuple[tuple[str, float, int], ...] = ()
    # Optional (additive in version 1): the tile's version (``Tile.version``); 0: none.
    tile_version: int = 0

    @property
    def index(self) -> TileIndex:
        return (self.i, self.j)

    @property
    def origin(self) -> tuple[float, float]:
        span = self.resolution * self.tile_size
        return (self.i * span, self.j * span)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.layers), self.tile_size, self.tile_size)

    def file_name(self) -> str:
        return tile_file_name(self.map_name, self.resolution, self.tile_size, self.i, self.j)


@dataclass(frozen=True)
class StoredTile:
    """A decoded tile: header and ``(N, T, T)`` int16 log-odds (a private, writable array)."""

    header: TileHeader
    data: Fixed

    def as_loader_result(self) -> LoaderResult:
        """The ``(layers, stack, stamp)`` triple of :data:`sogm_service.core.map.tiles.Loader`
        (with the decay stamps as a fourth item when the tile has any, and the applied marks as
        a fifth when it has any, and its version as a sixth when it has one)."""
        if self.header.tile_version:
            return (list(self.header.layers), self.data, self.header.stamp,
                    dict(self.header.decay), marks_of(self.header), self.header.tile_version)
        if self.header.applied:
            return (list(self.header.layers), self.data, self.header.stamp,
                    dict(self.header.decay), marks_of(self.header))
        if self.header.decay:
            return (list(self.header.layers), self.data, self.header.stamp,
                    dict(self.header.decay))
        return list(self.header.layers), self.data, self.header.stamp


@dataclass(frozen=True)
class Expectation:
    """What a store requires of every tile it loads."""

    map_name: str
    resolution: float
    tile_size: int
    frame: str | None = None


def tile_header(expect: Expectation, i: int, j: int, layers: Sequence[str], stamp: float,
                plane: LocalTangentPlane | None = None,
                decay: dict[str, float] | None = None,
                applied: dict[str, Mark] | None = None, version: int = 0) -> TileHeader:
    """The header of tile ``(i, j)`` of the map ``expect`` describes; with a local tangent
    ``plane`` (the map's datum) it carries the geodetic position of the tile's origin, and
    ``applied`` marks (:func:`bounded_marks`) and the tile's ``version`` when given."""
    datum = None
    if plane is not None:
        span = expect.resolution * expect.tile_size
        datum = plane.to_geodetic(i * span, j * span)
    return TileHeader(map_name=expect.map_name, frame=expect.frame or "map", i=i, j=j,
                      resolution=expect.resolution, tile_size=expect.tile_size,
                      layers=tuple(layers), stamp=float(stamp), datum=datum,
                      decay=tuple(sorted((str(k), float(v)) for k, v in (decay or {}).items())),
                      applied=bounded_marks(applied),
                      tile_version=version if 0 < version < _VERSION_END else 0)


def bounded_marks(applied: dict[str, Mark] | None) -> tuple[tuple[str, float, int], ...]:
    """``applied`` as the header holds it: sorted by key, only marks a reader accepts (a mark
    with an empty or over-long key, a non-finite stamp or a digest outside 64 bits is left
    out), and at most :data:`MAX_APPLIED` of them, the newest by stamp.  A mark left out
    costs only a handover's precision for that key (its journaled ISMs are replayed from the
    first), never the tile: a file a reader would refuse is never written."""
    marks = [(str(k), float(m[0]), int(m[1])) for k, m in (applied or {}).items()
             if 0 < len(str(k)) <= MAX_APPLIED_KEY and math.isfinite(float(m[0]))
             and 0 <= int(m[1]) < _DIGEST_END]
    if len(marks) > MAX_APPLIED:
        marks = sorted(marks, key=lambda m: (m[1], m[0]))[-MAX_APPLIED:]
    return tuple(sorted(marks))


def marks_of(header: TileHeader) -> dict[str, Mark]:
    """A header's ``applied`` marks as ``Tile.applied`` holds them."""
    return {k: (t, d) for k, t, d in header.applied}


def resolution_token(resolution: float) -> str:
    """``0.05 -> "0.050"``; more digits only when three decimals would not be exact."""
    short = f"{resolution:.3f}"
    if abs(float(short) - resolution) <= _RES_TOL * max(1.0, resolution):
        return short
    return f"{resolution:.10g}"


def tile_file_name(map_name: str, resolution: float, tile_size: int, i: int, j: int) -> str:
    """``sogm_<map>_r<res>_t<T>_i+0003_j-0012.tile``."""
    return f"{_file_stem(map_name, resolution, tile_size)}_{tile_token(i, j)}{SUFFIX}"


def _file_stem(map_name: str, resolution: float, tile_size: int) -> str:
    return f"sogm_{map_name}_r{resolution_token(resolution)}_t{tile_size}"


# -- encoding -------------------------------------------------------------------------------
def check_stack(layers: tuple[str, ...] | list[str], data: npt.NDArray[Any],
                tile_size: int) -> None:
    """Raise ``ValueError`` unless ``data`` is an ``(N, T, T)`` int16 stack for ``layers``."""
    if data.dtype != np.int16:
        raise ValueError(f"tile data must be int16, got {data.dtype}")
    if data.shape != (len(layers), tile_size, tile_size):
        raise ValueError(f"tile data shape {data.shape} != {(len(layers), tile_size, tile_size)}"
                         f" for {len(layers)} layers")
    if len(set(layers)) != len(layers) or not all(isinstance(n, str) and n for n in layers):
        raise ValueError(f"layer names must be unique non-empty strings: {list(layers)}")


def tile_to_bytes(header: TileHeader, data: npt.NDArray[np.int16],
                  level: int = DEFAULT_LEVEL) -> bytes:
    """Encode one tile (file and wire format, module docstring)."""
    check_stack(header.layers, data, header.tile_size)
    raw = np.ascontiguousarray(data, dtype="<i2").tobytes()
    payload = zlib.compress(raw, level)
    meta = _header_json(header, level, len(raw), payload)
    head = _PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(meta)) + meta
    return b"".join((head, _CRC.pack(zlib.crc32(head)), payload))


def _header_json(header: TileHeader, level: int, raw_len: int, payload: bytes) -> bytes:
    fields = {
        "map": header.map_name, "frame": header.frame, "i": header.i, "j": header.j,
        "resolution": header.resolution, "tile_size": header.tile_size,
        "origin": list(header.origin), "layers": list(header.layers), "dtype": "<i2",
        "shape": list(header.shape), "scale": header.scale,
        "datum": None if header.datum is None else header.datum.as_dict(),
        "stamp": header.stamp, "compression": "zlib", "level": level, "raw_len": raw_len,
        "payload_len": len(payload), "payload_crc32": zlib.crc32(payload),
        "written_unix": header.written_unix or time.time(),
    }
    if header.decay:
        fields["decay"] = dict(header.decay)
    if header.applied:
        fields["applied"] = {k: [t, d] for k, t, d in header.applied}
    if header.tile_version:
        fields["tile_version"] = header.tile_version
    return json.dumps(fields, separators=(",", ":"), allow_nan=False).encode()


def parse_prefix(head: bytes) -> tuple[int, int]:
    """``(header_len, bytes before the payload)`` from the first 16 bytes, or TileFormatError."""
    if head[:len(MAGIC)] != MAGIC[:len(head)]:
        raise TileFormatError(f"not a tile file (magic {bytes(head[:len(MAGIC)])!r})")
    if len(head) < _PREFIX.size:
        raise TileFormatError(f"truncated: {len(head)} bytes, shorter than the fixed prefix")
    _, version, _, hlen = _PREFIX.unpack_from(head)
    if version != FORMAT_VERSION:
        raise TileFormatError(f"unsupported format version {version} (this reads "
                              f"{FORMAT_VERSION})")
    if hlen > _MAX_HEADER:
        raise TileFormatError(f"header length {hlen} is implausible")
    return hlen, _PREFIX.size + hlen + _CRC.size


def parse_header(head: bytes) -> tuple[TileHeader, dict[str, Any], int]:
    """Check and decode the header part of a tile: ``(header, raw JSON fields, payload offset)``.

    ``head`` must hold at least everything before the payload.
    """
    hlen, start = parse_prefix(head)
    if len(head) < start:
        raise TileFormatError(f"truncated: header needs {start} bytes, have {len(head)}")
    (crc,) = _CRC.unpack_from(head, start - _CRC.size)
    if zlib.crc32(head[:start - _CRC.size]) != crc:
        raise TileFormatError("header checksum mismatch (corrupt header)")
    try:
        fields = json.loads(head[_PREFIX.size:_PREFIX.size + hlen])
        return _header_from_fields(fields), fields, start
    except TileFormatError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise TileFormatError(f"malformed header: {exc!r}") from None


def _header_from_fields(f: dict[str, Any]) -> TileHeader:
    layers = f["layers"]
    if not (isinstance(layers, list) and len(layers) <= _MAX_LAYERS
            and all(isinstance(n, str) for n in layers)):
        raise TileFormatError("header 'layers' must be a list of at most "
                              f"{_MAX_LAYERS} strings")
    datum = f["datum"]
    header = TileHeader(
        map_name=_typed(f, "map", str), frame=_typed(f, "frame", str), i=_typed(f, "i", int),
        j=_typed(f, "j", int), resolution=float(_typed(f, "resolution", (int, float))),
        tile_size=_typed(f, "tile_size", int), layers=tuple(layers),
        stamp=float(_typed(f, "stamp", (int, float))),
        datum=None if datum is None else GeoPoint(float(datum["latitude"]),
                                                  float(datum["longitude"]),
                                                  float(datum["altitude"])),
        scale=float(_typed(f, "scale", (int, float))), version=FORMAT_VERSION,
        written_unix=float(f.get("written_unix", 0.0)), decay=_decay_field(f, layers),
        applied=_applied_field(f), tile_version=_version_field(f))
    _check_header_consistency(header, f)
    return header


def _decay_field(f: dict[str, Any], layers: list[str]) -> tuple[tuple[str, float], ...]:
    """The optional ``decay`` field: ``{layer of this tile: finite stamp}``."""
    decay = f.get("decay")
    if decay is None:
        return ()
    if not isinstance(decay, dict) or len(decay) > len(layers):
        raise TileFormatError("header 'decay' must map this tile's layers to stamps")
    out = []
    for name, t in decay.items():
        if name not in layers or isinstance(t, bool) or not isinstance(t, (int, float)) \
                or not math.isfinite(t):
            raise TileFormatError(f"header 'decay' entry {name!r}: {t!r} is not a stamp of "
                                  "one of the tile's layers")
        out.append((name, float(t)))
    return tuple(sorted(out))


def _applied_field(f: dict[str, Any]) -> tuple[tuple[str, float, int], ...]:
    """The optional ``applied`` field: ``{ISM key: [finite stamp, digest in [0, 2**64)]}``."""
    applied = f.get("applied")
    if applied is None:
        return ()
    if not isinstance(applied, dict) or len(applied) > MAX_APPLIED:
        raise TileFormatError(f"header 'applied' must map at most {MAX_APPLIED} ISM keys to "
                              "[stamp, digest]")
    out = []
    for key, mark in applied.items():
        if not (isinstance(key, str) and 0 < len(key) <= MAX_APPLIED_KEY
                and isinstance(mark, list) and len(mark) == 2):
            raise TileFormatError(f"header 'applied' entry {str(key)[:80]!r} is not an ISM key "
                                  "with [stamp, digest]")
        t, d = mark
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) \
                or isinstance(d, bool) or not isinstance(d, int) or not 0 <= d < _DIGEST_END:
            raise TileFormatError(f"header 'applied' entry {key[:80]!r}: {mark!r} is not a "
                                  "finite stamp and a 64-bit digest")
        out.append((key, float(t), d))
    return tuple(sorted(out))


def _version_field(f: dict[str, Any]) -> int:
    """The optional ``tile_version`` field: an integer in ``[1, 2**63)`` (absent: 0)."""
    v = f.get("tile_version", 0)
    if isinstance(v, bool) or not isinstance(v, int) or not (v == 0 or 0 < v < _VERSION_END):
        raise TileFormatError(f"header 'tile_version' {str(v)[:40]} is not a tile version")
    return v


def _typed(fields: dict[str, Any], key: str, kind: type | tuple[type, ...]) -> Any:
    value = fields[key]
    if isinstance(value, bool) or not isinstance(value, kind):
        raise TileFormatError(f"header field {key!r} has the wrong type: {value!r}")
    return value


def _check_header_consistency(h: TileHeader, f: dict[str, Any]) -> None:
    if not (math.isfinite(h.resolution) and h.resolution > 0):
        raise TileFormatError(f"bad resolution {h.resolution}")
    if h.tile_size <= 0 or h.tile_size & (h.tile_size - 1) or h.tile_size > 1 << 16:
        raise TileFormatError(f"bad tile size {h.tile_size}")
    if f.get("dtype") != "<i2" or f.get("compression") != "zlib":
        raise TileFormatError(f"unsupported dtype/compression {f.get('dtype')!r}/"
                              f"{f.get('compression')!r}")
    if list(f.get("shape", [])) != list(h.shape):
        raise TileFormatError(f"shape {f.get('shape')} disagrees with {len(h.layers)} layers "
                              f"of {h.tile_size}x{h.tile_size}")
    if f.get("raw_len") != 2 * math.prod(h.shape):
        raise TileFormatError(f"raw length {f.get('raw_len')} disagrees with shape {h.shape}")
    if h.scale != logodds.SCALE:
        raise TileFormatError(f"log-odds scale {h.scale} != this build's {logodds.SCALE}")
    if len(set(h.layers)) != len(h.layers) or not all(h.layers):
        raise TileFormatError(f"layer names must be unique and non-empty: {list(h.layers)}")
    for key in ("payload_len", "payload_crc32"):
        _typed(f, key, int)


def check_expectation(header: TileHeader, expect: Expectation) -> None:
    """Raise TileFormatError unless the tile belongs to the map ``expect`` describes."""
    if header.map_name != expect.map_name:
        raise TileFormatError(f"map {header.map_name!r} != store's {expect.map_name!r}")
    if abs(header.resolution - expect.resolution) > _RES_TOL * max(1.0, expect.resolution):
        raise TileFormatError(f"resolution {header.resolution} != store's {expect.resolution}")
    if header.tile_size != expect.tile_size:
        raise TileFormatError(f"tile size {header.tile_size} != store's {expect.tile_size}")
    if expect.frame is not None and header.frame != expect.frame:
        raise TileFormatError(f"frame {header.frame!r} != store's {expect.frame!r}")


def tile_from_bytes(blob: bytes, expect: Expectation | None = None) -> StoredTile:
    """Decode and fully validate one tile (file or wire bytes); TileFormatError on any fault."""
    header, fields, start = parse_header(blob[:_header_end(blob)])
    if expect is not None:
        check_expectation(header, expect)
    payload = memoryview(blob)[start:]
    if len(payload) != fields["payload_len"]:
        what = "truncated" if len(payload) < fields["payload_len"] else "trailing bytes"
        raise TileFormatError(f"{what}: payload is {len(payload)} bytes, header says "
                              f"{fields['payload_len']}")
    if zlib.crc32(payload) != fields["payload_crc32"]:
        raise TileFormatError("payload checksum mismatch (corrupt data)")
    return StoredTile(header, _decompress(payload, header))


def _header_end(blob: bytes) -> int:
    try:
        return parse_prefix(blob[:_PREFIX.size])[1]
    except TileFormatError:
        return len(blob)  # parse_header repeats the check and raises with the reason


def _decompress(payload: memoryview, header: TileHeader) -> Fixed:
    raw_len = 2 * math.prod(header.shape)
    try:
        d = zlib.decompressobj()
        raw = d.decompress(payload, raw_len + 1)  # bounded: a bad stream cannot balloon
    except zlib.error as exc:
        raise TileFormatError(f"payload does not decompress: {exc}") from None
    if len(raw) != raw_len or not d.eof or d.unused_data:
        raise TileFormatError(f"payload decompresses to {len(raw)} bytes, expected {raw_len}")
    data = np.frombuffer(raw, dtype="<i2").astype(np.int16).reshape(header.shape)
    if data.size and (int(data.min()) < -logodds.MAX_STATE or int(data.max()) > logodds.MAX_STATE):
        raise TileFormatError(f"log-odds outside ±{logodds.MAX_STATE} (fusion would overflow)")
    return data
