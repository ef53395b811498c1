"""The directory backend of the tile store: one file per tile (:mod:`sogm_service.store.format`).

Durability: :meth:`DirectoryStore.write` writes a temporary file in the same directory, fsyncs it,
renames it over the old file and fsyncs the directory, so a crash at any point leaves either the
old or the new tile.  Writes never block ingestion:
:class:`~sogm_service.store.writer.TileWriter` does them on a background thread from snapshots
the caller copied under its own lock (the paper's double buffer).  One process owns a store
directory at a time (an exclusive ``flock`` on ``.lock``); read-only users (``sogm-service tiles
ls``) take no lock.

A file failing any check of the format is *reported* with a reason, logged, and moved into
``quarantine/`` with a ``.reason.txt`` next to it; it is never loaded and never fatal.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Final

from sogm_service.core.geodesy import GeodeticLike
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.store.base import TileStoreBase
from sogm_service.store.format import read_tile_header
from sogm_service.store.protocol import StoreProblem, TileFileInfo
from sogm_service.wire.errors import StoreLockedError, TileFormatError
from sogm_service.wire.tilefile import (
    DEFAULT_LEVEL,
    SUFFIX,
    StoredTile,
    TileHeader,
    _file_stem,
    check_expectation,
    tile_file_name,
    tile_from_bytes,
)

log = logging.getLogger(__name__)

QUARANTINE_DIR: Final = "quarantine"
LOCK_FILE: Final = ".lock"
_tmp_counter = itertools.count()


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, blob: bytes) -> None:
    """Write ``blob`` to ``path`` so that a crash leaves either the old or the new content."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{next(_tmp_counter)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(path.parent)  # the rename itself must survive a power loss


def lock_directory(directory: Path) -> int:
    """Take the exclusive lock of a store directory; returns the fd to ``os.close`` to release.

    ``flock`` dies with its process, so a killed server never leaves a stale lock.
    """
    fd = os.open(directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _lock_holder(fd)
        os.close(fd)
        who = f"process {holder}" if holder is not None else "another process"
        raise StoreLockedError(f"{directory} is in use by {who} (lock {LOCK_FILE}); "
                               "one writer per store directory", str(directory),
                               holder) from None
    with contextlib.suppress(OSError):  # the holder's pid, for the next one's error message
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def _lock_holder(fd: int) -> int | None:
    """The pid the lock's holder wrote into the lock file, if any."""
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None



class DirectoryStore(TileStoreBase):
    """A directory of tile files for one map (module docstring: format and guarantees).

    Thread-safe: the writer thread writes while the server thread indexes and loads.
    """

    shared = False  # one process owns a store directory (its lock)

    def __init__(self, directory: Path | str, map_name: str, resolution: float, tile_size: int,
                 frame: str | None = "map", datum: GeodeticLike | None = None,
                 level: int = DEFAULT_LEVEL, readonly: bool = False, lock: bool = True) -> None:
        """``frame``: the map frame every tile must carry (None: any, for inspection tools).
        ``readonly``: never write, quarantine or delete (for inspection tools).
        ``lock``: take the directory's exclusive lock (:class:`StoreLockedError` when another
        process holds it); pass False only when the caller holds it (:func:`lock_directory`).
        """
        super().__init__(map_name, resolution, tile_size, frame, datum, level, readonly)
        self.directory = Path(directory)
        self._lock_fd: int | None = None
        if not readonly:
            self.directory.mkdir(parents=True, exist_ok=True)
            if lock:
                self._lock_fd = lock_directory(self.directory)

    # -- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        """Release the directory lock (the kernel also releases it if the process dies)."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # -- names ----------------------------------------------------------------------------
    def path_for(self, i: int, j: int) -> Path:
        e = self.expect
        return self.directory / tile_file_name(e.map_name, e.resolution, e.tile_size, i, j)

    def _glob(self) -> Iterator[Path]:
        e = self.expect
        return self.directory.glob(f"{_file_stem(e.map_name, e.resolution, e.tile_size)}_*"
                                   f"{SUFFIX}")

    # -- index ----------------------------------------------------------------------------
    def index(self) -> dict[TileIndex, TileFileInfo]:
        """Scan the directory: check every tile header, quarantine the bad, drop stale temps."""
        if not self.readonly:
            self._remove_stale_temps()
        found: dict[TileIndex, TileFileInfo] = {}
        for path in sorted(self._glob()):
            info = self._index_one(path)
            if info is not None:
                found[info.header.index] = info
        with self._lock:
            self._index = found
            return dict(found)

    def _index_one(self, path: Path) -> TileFileInfo | None:
        try:
            header, size = read_tile_header(path)
            check_expectation(header, self.expect)
            if header.file_name() != path.name:
                raise TileFormatError(f"file name disagrees with header (tile "
                                      f"{header.index} belongs in {header.file_name()})")
        except (TileFormatError, OSError) as exc:
            self._reject(path, _reason(exc))
            return None
        return TileFileInfo(header, path, size)

    def _remove_stale_temps(self) -> None:
        e = self.expect
        for tmp in self.directory.glob(f".{_file_stem(e.map_name, e.resolution, e.tile_size)}"
                                       f"_*{SUFFIX}.tmp-*"):
            log.warning("removing %s: an interrupted write (the previous tile file is intact)",
                        tmp.name)
            with contextlib.suppress(OSError):
                tmp.unlink()

    # -- reading --------------------------------------------------------------------------
    def _read_valid(self, i: int, j: int) -> tuple[bytes, StoredTile] | None:
        path = self.path_for(i, j)
        try:
            with open(path, "rb") as fh:
                inode = os.fstat(fh.fileno()).st_ino
                blob = fh.read()
        except FileNotFoundError:
            with self._lock:
                self._index.pop((i, j), None)
            return None
        try:
            tile = tile_from_bytes(blob, self.expect)
            if tile.header.index != (i, j):
                raise TileFormatError(f"file of tile {(i, j)} holds tile {tile.header.index}")
        except TileFormatError as exc:
            self._reject(path, exc.reason, inode)
            return None
        return blob, tile

    # -- writing --------------------------------------------------------------------------
    def _store(self, header: TileHeader, blob: bytes) -> TileFileInfo:
        if self.readonly:
            raise PermissionError(f"store {self.directory} was opened read-only")
        path = self.path_for(header.i, header.j)
        with self._lock:  # serialises the rename against a concurrent quarantine move
            atomic_write(path, blob)
            info = TileFileInfo(header, path, len(blob))
            self._index[header.index] = info
        return info

    # -- rejects --------------------------------------------------------------------------
    def _reject(self, path: Path, reason: str, inode: int | None = None) -> None:
        """Report a bad file and move it into ``quarantine/`` (read-only stores only report)."""
        moved: Path | None = None
        with self._lock:
            if not self.readonly and _same_file(path, inode):
                moved = _quarantine(path, reason)
            for index, info in list(self._index.items()):
                if info.path == path:
                    del self._index[index]
            self.problems.append(StoreProblem(path, reason, moved))
        log.warning("tile file %s rejected: %s%s", path, reason,
                    f"; moved to {moved}" if moved else "")

    def remove(self, i: int, j: int) -> bool:
        """Delete tile ``(i, j)``'s file (a cluster member that no longer owns the tile);
        True when there was one."""
        if self.readonly:
            raise PermissionError(f"store {self.directory} was opened read-only")
        path = self.path_for(i, j)
        with self._lock:
            self._index.pop((i, j), None)
            try:
                path.unlink()
            except FileNotFoundError:
                return False
            _fsync_dir(self.directory)
        return True


def _same_file(path: Path, inode: int | None) -> bool:
    """Whether ``path`` still is the file that was read (a writer may have replaced it)."""
    if inode is None:
        return path.exists()
    try:
        return path.stat().st_ino == inode
    except FileNotFoundError:
        return False


def _quarantine(path: Path, reason: str) -> Path | None:
    qdir = path.parent / QUARANTINE_DIR
    try:
        qdir.mkdir(exist_ok=True)
        target = qdir / path.name
        if target.exists():  # keep every rejected version
            target = qdir / f"{path.name}.{time.strftime('%Y%m%dT%H%M%S')}-{time.monotonic_ns()}"
        os.replace(path, target)
        target.with_name(target.name + ".reason.txt").write_text(reason + "\n")
        return target
    except OSError as exc:
        log.error("could not quarantine %s: %s", path, exc)
        return None


def _reason(exc: BaseException) -> str:
    return exc.reason if isinstance(exc, TileFormatError) else f"{type(exc).__name__}: {exc}"


