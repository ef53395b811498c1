"""sogm-service tiles import: validate tile files and copy them into a store (under its lock);
a rejected file is reported with its reason and left where it was."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TextIO

from sogm_service.apps.options import UsageError
from sogm_service.store.directory import DirectoryStore, lock_directory
from sogm_service.wire.errors import TileFormatError
from sogm_service.wire.tilefile import SUFFIX, MapKey, TileHeader, tile_from_bytes


def cmd_import(args: argparse.Namespace, out: TextIO) -> int:
    dest: Path = args.into
    dest.mkdir(parents=True, exist_ok=True)
    lock_fd = lock_directory(dest)
    try:
        stores: dict[MapKey, DirectoryStore] = {}
        counts = {"imported": 0, "skipped": 0, "rejected": 0}
        from tqdm import tqdm

        files = _source_files(args.sources)
        for path in tqdm(files, desc="tiles import", unit="tile", file=sys.stderr,
                         disable=None, leave=False):
            outcome = _import_one(path, stores, dest, args.on_conflict)
            counts[outcome.split(":")[0]] += 1
            print(f"{outcome.split(':')[0]:<8} {path}{_detail(outcome)}", file=out)
    finally:
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


def _import_one(path: Path, stores: dict[MapKey, DirectoryStore], dest: Path,
                policy: str) -> str:
    """One file -> ``"imported"``, ``"skipped:<why>"`` or ``"rejected:<reason>"``."""
    try:
        blob = path.read_bytes()
        header = tile_from_bytes(blob).header
        store = _store_for(header, stores, dest)
        existing = store.indexed().get(header.index)
        if existing is not None and not _replace(existing.header, header, policy):
            return f"skipped:tile {header.index} exists (stamp {existing.header.stamp})"
        store.write_bytes(blob)
    except (TileFormatError, OSError) as exc:
        return f"rejected:{exc.reason if isinstance(exc, TileFormatError) else exc}"
    return "imported"


def _replace(old: TileHeader, new: TileHeader, policy: str) -> bool:
    return policy == "overwrite" or (policy == "newer" and new.stamp > old.stamp)


def _store_for(header: TileHeader, stores: dict[MapKey, DirectoryStore],
               dest: Path) -> DirectoryStore:
    """The destination store of the tile's map; its frame is the one already stored, if any."""
    key = (header.map_name, header.resolution, header.tile_size)
    if key not in stores:
        probe = DirectoryStore(dest, *key, frame=None, readonly=True)
        frames = {info.header.frame for info in probe.index().values()}
        frame = frames.pop() if len(frames) == 1 else header.frame
        store = DirectoryStore(dest, *key, frame=frame, lock=False)
        store.index()
        stores[key] = store
    return stores[key]

