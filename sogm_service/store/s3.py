"""The object-store backend of the tile store: one object per tile in an S3 bucket
(``[store] url = "s3://bucket/prefix"``), in the same tile format and under the same names as
the directory store's files (:mod:`sogm_service.wire.tilefile`).

* **Complete or absent**: an S3 PUT replaces an object whole, so a reader sees the old or the
  new tile, never a mix; a crash mid-upload leaves the old object.
* **Validated**: a tile object failing any check of the format is never returned; it is
  copied to ``<prefix>/quarantine/`` with a ``.reason.txt`` beside it, then deleted (only if
  it is still the object that was read), and reported in :attr:`S3Store.problems`.
* **Fenced writes**: several servers may share one bucket (a cluster), so every write is
  conditional on the object as this store last saw it: ``IfMatch`` on its ETag, or
  ``IfNoneMatch="*"`` for a tile it saw absent or never saw.  A write replaces a stored tile
  only if this copy holds every ISM the stored one holds (by their applied marks: the last
  ISM fused per ISM key), checked against the copy this store last saw and, when the
  condition fails (another server wrote the tile since), against the object now stored.
  Otherwise the write is refused with ``StoreConflictError``: a server that lost a tile
  (paused, partitioned) never overwrites a newer copy, nor does an import.
* **Credentials and region** come from boto3's usual chain (the ``AWS_*`` environment, the
  shared config and credentials files, instance roles); ``endpoint_url`` points it at another
  S3 server (SeaweedFS, MinIO, a cloud's regional endpoint).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import PurePath
from typing import Any, Final

from sogm_service.core.geodesy import GeodeticLike
from sogm_service.core.map.tiletypes import Mark, TileIndex
from sogm_service.store.base import TileStoreBase
from sogm_service.store.protocol import StoreProblem, TileFileInfo
from sogm_service.store.s3objects import (
    ABSENT,
    PRECONDITION,
    S3Location,
    S3Objects,
    error_code,
    s3_client,
)
from sogm_service.wire.errors import StoreConflictError, StoreUnavailableError, TileFormatError
from sogm_service.wire.tilefile import (
    DEFAULT_LEVEL,
    MAX_APPLIED,
    StoredTile,
    TileHeader,
    _file_stem,
    check_expectation,
    marks_of,
    tile_file_name,
    tile_from_bytes,
)

log = logging.getLogger(__name__)

QUARANTINE: Final = "quarantine"
WRITE_ATTEMPTS: Final = 4  # a write that keeps meeting newer objects it may replace gives up


def holds_all(ours: dict[str, Mark], theirs: dict[str, Mark]) -> bool:
    """Whether a copy with marks ``ours`` holds every ISM one with marks ``theirs`` holds:
    per ISM key, the same last ISM or a later one.  (A header keeps at most
    :data:`MAX_APPLIED` marks, the newest: a key missing from a full set of ours and older
    than all of them counts as held.)"""
    oldest = min((m[0] for m in ours.values()), default=math.inf) \
        if len(ours) >= MAX_APPLIED else -math.inf
    for key, mark in theirs.items():
        mine = ours.get(key)
        if mine is None:
            if mark[0] < oldest:
                continue
            return False
        if mine != mark and mine[0] <= mark[0]:
            return False
    return True


class S3Store(TileStoreBase):
    """The tiles of one map in an S3 bucket (module docstring: format and guarantees).

    Thread-safe: the writer thread writes while the server thread indexes and loads."""

    shared = True  # other servers may write the same objects

    def __init__(self, location: S3Location | str, map_name: str, resolution: float,
                 tile_size: int, frame: str | None = "map", datum: GeodeticLike | None = None,
                 level: int = DEFAULT_LEVEL, readonly: bool = False,
                 endpoint_url: str | None = None, client: Any = None) -> None:
        """``frame``: the map frame every tile must carry (None: any, for inspection tools).
        ``readonly``: never write, quarantine or delete (for inspection tools)."""
        super().__init__(map_name, resolution, tile_size, frame, datum, level, readonly)
        self.location = S3Location.parse(location) if isinstance(location, str) else location
        self.objects = S3Objects(self.location, client or s3_client(endpoint_url))
        self.writes_fenced = 0
        self._etags: dict[TileIndex, str | None] = {}  # as last seen; None: seen absent
        self._marks: dict[TileIndex, dict[str, Mark]] = {}  # of the copy last seen

    @property
    def url(self) -> str:
        return self.location.url

    # -- names ----------------------------------------------------------------------------
    def key_for(self, i: int, j: int) -> str:
        e = self.expect
        return self.location.key(tile_file_name(e.map_name, e.resolution, e.tile_size, i, j))

    # -- index ----------------------------------------------------------------------------
    def index(self) -> dict[TileIndex, TileFileInfo]:
        """List the map's objects and check every tile header (one ranged GET each)."""
        e = self.expect
        found: dict[TileIndex, TileFileInfo] = {}
        try:
            for key, size, _ in self.objects.list(_file_stem(e.map_name, e.resolution,
                                                             e.tile_size) + "_"):
                info = self._index_one(key, size)
                if info is not None:
                    found[info.header.index] = info
        except Exception as exc:  # endpoint, bucket, credentials: say which store and why
            raise StoreUnavailableError(f"tile store {self.url} cannot be listed: "
                                        f"{exc}") from exc
        with self._lock:
            self._index = found
            return dict(found)

    def _index_one(self, key: str, size: int) -> TileFileInfo | None:
        etag = None
        try:
            got = self.objects.header(key)
            if got is None:
                return None  # deleted since the listing
            header, expected, etag = got
            if size != expected:
                what = "truncated" if size < expected else "trailing bytes"
                raise TileFormatError(f"{what}: object is {size} bytes, header says {expected}")
            check_expectation(header, self.expect)
            if self.location.key(header.file_name()) != key:
                raise TileFormatError(f"object name disagrees with header (tile "
                                      f"{header.index} belongs in {header.file_name()})")
        except TileFormatError as exc:
            self._reject(key, exc.reason, etag or self.objects.etag(key))
            return None
        with self._lock:
            self._etags[header.index] = etag
            self._marks[header.index] = marks_of(header)
        return TileFileInfo(header, self.location.where(key), size)

    # -- reading --------------------------------------------------------------------------
    def _read_valid(self, i: int, j: int) -> tuple[bytes, StoredTile] | None:
        key = self.key_for(i, j)
        got = self.objects.get(key)
        if got is None:
            with self._lock:
                self._index.pop((i, j), None)
                self._etags[(i, j)] = None
            return None
        blob, etag = got
        try:
            tile = tile_from_bytes(blob, self.expect)
            if tile.header.index != (i, j):
                raise TileFormatError(f"object of tile {(i, j)} holds tile {tile.header.index}")
        except TileFormatError as exc:
            self._reject(key, exc.reason, etag)
            return None
        with self._lock:
            self._etags[(i, j)] = etag
            self._marks[(i, j)] = marks_of(tile.header)
        return blob, tile

    # -- writing --------------------------------------------------------------------------
    def _store(self, header: TileHeader, blob: bytes) -> TileFileInfo:
        if self.readonly:
            raise PermissionError(f"store {self.url} was opened read-only")
        index, key, ours = header.index, self.key_for(header.i, header.j), marks_of(header)
        for _ in range(WRITE_ATTEMPTS):
            with self._lock:
                seen, marks = self._etags.get(index), self._marks.get(index, {})
            if seen and not holds_all(ours, marks):
                self._refuse(index)
            try:
                etag = self.objects.put(key, blob, **({"IfMatch": seen} if seen
                                                      else {"IfNoneMatch": "*"}))
            except Exception as exc:
                if error_code(exc) not in PRECONDITION:
                    raise
                self._check_replaceable(index, key, ours)
                continue
            info = TileFileInfo(header, self.location.where(key), len(blob))
            with self._lock:
                self._etags[index] = etag
                self._marks[index] = ours
                self._index[index] = info
            return info
        raise StoreConflictError(f"tile {index} at {self.url} kept changing during "
                                 f"{WRITE_ATTEMPTS} writes", index)

    def _check_replaceable(self, index: TileIndex, key: str, ours: dict[str, Mark]) -> None:
        """The stored object changed: learn its ETag if this copy may replace it, else raise
        StoreConflictError (it holds an ISM this copy lacks)."""
        try:
            got = self.objects.header(key)
        except TileFormatError:  # a damaged object holds nothing to keep
            got = None
            etag = self.objects.etag(key)
        else:
            etag = None if got is None else got[2]
        if got is not None and not holds_all(ours, marks_of(got[0])):
            self._refuse(index)
        with self._lock:
            self._etags[index] = etag
            self._marks[index] = {} if got is None else marks_of(got[0])

    def _refuse(self, index: TileIndex) -> None:
        self.writes_fenced += 1
        log.warning("tile %s at %s: not written, the stored copy holds ISMs this one lacks "
                    "(another server wrote it)", index, self.url)
        raise StoreConflictError(f"tile {index} at {self.url} holds ISMs this copy lacks "
                                 "(another server wrote it)", index)

    def remove(self, i: int, j: int) -> bool:
        """Delete tile ``(i, j)``'s object if it is still the one this store last saw; True
        when it was deleted."""
        if self.readonly:
            raise PermissionError(f"store {self.url} was opened read-only")
        key = self.key_for(i, j)
        with self._lock:
            self._index.pop((i, j), None)
            seen = self._etags.pop((i, j), None)
            self._marks.pop((i, j), None)
        if seen is None:
            return False
        try:
            self.objects.client.delete_object(Bucket=self.location.bucket, Key=key,
                                              IfMatch=seen)
        except Exception as exc:
            if error_code(exc) in PRECONDITION | ABSENT:
                return False
            raise
        return True

    # -- rejects --------------------------------------------------------------------------
    def _reject(self, key: str, reason: str, etag: str | None) -> None:
        """Report a bad object and move it to ``quarantine/`` (read-only stores only
        report); the original is deleted only if it is still the object that was read."""
        moved: PurePath | None = None
        if not self.readonly and etag:
            moved = self._quarantine(key, reason, etag)
        with self._lock:
            for index, info in list(self._index.items()):
                if info.path == self.location.where(key):
                    del self._index[index]
            self.problems.append(StoreProblem(self.location.where(key), reason,
                                              moved))
        log.warning("tile object %s rejected: %s%s", self.location.where(key), reason,
                    f"; moved to {moved}" if moved else "")

    def _quarantine(self, key: str, reason: str, etag: str) -> PurePath | None:
        name = key.rsplit("/", 1)[-1]
        target = self.location.key(f"{QUARANTINE}/{name}.{time.strftime('%Y%m%dT%H%M%S')}-"
                                   f"{time.monotonic_ns()}")
        client, bucket = self.objects.client, self.location.bucket
        try:
            client.copy_object(Bucket=bucket, Key=target, CopySourceIfMatch=etag,
                               CopySource={"Bucket": bucket, "Key": key})
            client.put_object(Bucket=bucket, Key=target + ".reason.txt",
                              Body=(reason + "\n").encode(), ContentType="text/plain")
            client.delete_object(Bucket=bucket, Key=key, IfMatch=etag)
        except Exception as exc:
            log.error("could not quarantine %s: %s", self.location.where(key), exc)
            return None
        return self.location.where(target)
