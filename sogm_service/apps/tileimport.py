"""sogm-service tiles import: validate tile files and copy them into a store (a directory under
its lock, or an object store with fenced writes); a rejected file is reported with its reason
and left where it was."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TextIO

from sogm_service.apps.options import UsageError
from sogm_service.store.directory import DirectoryStore, lock_directory
from sogm_service.store.protocol import TileStore
from sogm_service.wire.errors import StoreConflictError, TileFormatError
from sogm_service.wire.tilefile import SUFFIX, MapKey, TileHeader, tile_from_bytes


def is_url(store: str | Path) -> bool:
    """Whether a store argument names an object store (``s3://bucket/prefix``)."""
    return str(store).startswith("s3://")


def open_readonly(store: str, key: MapKey, endpoint_url: str | None) -> TileStore:
    """A store of one map, opened to read only (any frame)."""
    if is_url(store):
        from sogm_service.store.s3 import S3Store

        return S3Store(store, *key, frame=None, readonly=True, endpoint_url=endpoint_url)
    return DirectoryStore(store, *key, frame=None, readonly=True)


def cmd_import(args: argparse.Namespace, out: TextIO) -> int:
    into = str(args.into)
    lock_fd = None
    if not is_url(into):  # an object store fences each write instead
        Path(into).mkdir(parents=True, exist_ok=True)
        lock_fd = lock_directory(Path(into))
    try:
        stores: dict[MapKey, TileStore] = {}
        counts = {"imported": 0, "skipped": 0, "rejected": 0}
        from tqdm import tqdm

        files = _source_files(args.sources)
        for path in tqdm(files, desc="tiles import", unit="tile", file=sys.stderr,
                         disable=None, leave=False):
            outcome = _import_one(path, stores, into, args.on_conflict,
                                  getattr(args, "endpoint_url", None))
            counts[outcome.split(":")[0]] += 1
            print(f"{outcome.split(':')[0]:<8} {path}{_detail(outcome)}", file=out)
    finally:
        if lock_fd is not None:
            os.close(lock_fd)
    print(", ".join(f"{v} {k}" for k, v in counts.items()), file=out)
    return 1 if counts["rejected"] else 0


def _detail(outcome: str) -> str:
    _, _, detail = outcome.partition(":")
    return f": {detail}" if detail else ""


def _source_files(sources: list[Path]) -> list[Path]:
    files: list[Path] = []
    for src in sources:
        if src.is_dir():
            files.extend(sorted(src.glob(f"*{SUFFIX}")))
        elif src.is_file():
            files.append(src)
        else:
            raise UsageError(f"{src} does not exist")
    return files


def _import_one(path: Path, stores: dict[MapKey, TileStore], dest: str, policy: str,
                endpoint_url: str | None = None) -> str:
    """One file -> ``"imported"``, ``"skipped:<why>"`` or ``"rejected:<reason>"``."""
    try:
        blob = path.read_bytes()
        header = tile_from_bytes(blob).header
        store = _store_for(header, stores, dest, endpoint_url)
        existing = store.indexed().get(header.index)
        if existing is not None and not _replace(existing.header, header, policy):
            return f"skipped:tile {header.index} exists (stamp {existing.header.stamp})"
        store.write_bytes(blob)
    except StoreConflictError as exc:
        return f"skipped:{exc.message}"
    except (TileFormatError, OSError) as exc:
        return f"rejected:{exc.reason if isinstance(exc, TileFormatError) else exc}"
    return "imported"


def _replace(old: TileHeader, new: TileHeader, policy: str) -> bool:
    return policy == "overwrite" or (policy == "newer" and new.stamp > old.stamp)


def _store_for(header: TileHeader, stores: dict[MapKey, TileStore], dest: str,
               endpoint_url: str | None) -> TileStore:
    """The destination store of the tile's map; its frame is the one already stored, if any."""
    key = (header.map_name, header.resolution, header.tile_size)
    if key not in stores:
        probe = open_readonly(dest, key, endpoint_url)
        frames = {info.header.frame for info in probe.index().values()}
        frame = frames.pop() if len(frames) == 1 else header.frame
        store: TileStore
        if is_url(dest):
            from sogm_service.store.s3 import S3Store

            store = S3Store(dest, *key, frame=frame, endpoint_url=endpoint_url)
        else:
            store = DirectoryStore(dest, *key, frame=frame, lock=False)
        store.index()
        stores[key] = store
    return stores[key]

