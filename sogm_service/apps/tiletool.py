"""sogm-service tiles ls|export|import: look at, export and import stored tiles.

Examples:

    sogm-service tiles ls /var/lib/sogm/tiles                 # one line per tile, bad files flagged
    sogm-service tiles ls /var/lib/sogm/tiles --verify        # also check every payload checksum
    sogm-service tiles export /var/lib/sogm/tiles --tile 3 -12 --out t.png    # t_<layer>.png
    sogm-service tiles export DIR --range 0 0 2 1 --out region.npy            # + region.npy.json
    sogm-service tiles export DIR --box -5 -5 20 10 --layers obstacle --out box.png
    sogm-service tiles import backup/ --into /var/lib/sogm/tiles --on-conflict newer
    sogm-service tiles ls s3://sogm-tiles/site-a --endpoint-url http://127.0.0.1:8333
    sogm-service tiles import backup/ --into s3://sogm-tiles/site-a

A store is a directory or an object store URL, s3://bucket/prefix (credentials and region from
the usual AWS environment and config files; --endpoint-url for another S3 server than the
cloud's).  ls and export only read (no lock, no quarantine): they work on a live server's
store.  import into a directory takes the store's lock, so stop the server first; into an
object store it writes as a server does, fenced, so it never replaces a stored tile holding an
ISM the imported one lacks.  Every file is fully validated and a rejected one is reported with
its reason and left where it was.  ls exits 1 when it lists a bad
file, import when it rejected one; a refusal (no such directory, a store in use) exits 2.

PNG export: one image per layer, probabilities as grey (free white, occupied black), unknown
(log-odds exactly 0, or no tile) in a distinct blue tint, north up.
.npy export: the stacked (N, H, W) int16 fixed-point log-odds (1000 units per nat, 0 =
unknown), with a .json sidecar naming the layers, resolution and origin.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path, PurePath
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from sogm_service.apps.options import (
    PROG,
    UsageError,
    command,
    fail,
    standalone,
    subcommands,
)
from sogm_service.apps.tileimport import is_url, open_readonly
from sogm_service.core import logodds
from sogm_service.core.geometry import TileLattice
from sogm_service.core.map.tiletypes import TileIndex
from sogm_service.store.format import read_tile_file, read_tile_header
from sogm_service.store.protocol import TileStore
from sogm_service.wire.errors import (
    ConfigError,
    StoreLockedError,
    StoreUnavailableError,
    TileFormatError,
)
from sogm_service.wire.tilefile import SUFFIX, MapKey, StoredTile, TileHeader, tile_from_bytes

_CELL_EPS = 1e-9
MAX_EXPORT_CELLS = 1 << 26  # per layer: 64 M cells (8192 x 8192) keeps an export in memory


# -- parser ---------------------------------------------------------------------------------
def add_parser(subparsers: Any) -> None:
    add_tiles_parser(subparsers)


def add_tiles_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``tiles`` with its sub-commands to an argparse ``add_subparsers()`` object."""
    tiles = command(subparsers, "tiles", "list, export and import stored tiles",
                    description=__doc__ or "")
    _fill_parser(tiles)
    return tiles


def build_parser() -> argparse.ArgumentParser:
    """The tiles command on its own (for scripts and tests)."""
    parser = standalone(f"{PROG} tiles", description=__doc__ or "")
    _fill_parser(parser)
    return parser


def _fill_parser(p: argparse.ArgumentParser) -> None:
    p.set_defaults(handler=run_tiles)
    sub = subcommands(p, "tiles_command")
    ls = command(sub, "ls", "list the tiles of a store")
    ls.add_argument("directory", metavar="STORE", help=STORE_HELP)
    ls.add_argument("--verify", action="store_true",
                    help="also read every payload and check its checksum")
    _map_filter_args(ls)
    ex = command(sub, "export", "write a tile or a region to PNG or .npy")
    ex.add_argument("directory", metavar="STORE", help=STORE_HELP)
    ex.add_argument("--out", type=Path, required=True,
                    help="file.png (one <stem>_<layer>.png per layer) or file.npy")
    where = ex.add_mutually_exclusive_group(required=True)
    where.add_argument("--tile", type=int, nargs=2, metavar=("I", "J"),
                       help="one tile, by its indices on the tile lattice")
    where.add_argument("--range", type=int, nargs=4, metavar=("I0", "J0", "I1", "J1"),
                       help="tiles I0..I1 x J0..J1 inclusive (tile indices)")
    where.add_argument("--box", type=float, nargs=4, metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                       help="metric box in the map frame (m)")
    ex.add_argument("--layers", default=None, metavar="A,B",
                    help="comma-separated layers (default: all)")
    ex.add_argument("--scale", type=int, default=1, metavar="PX",
                    help="PNG pixels per cell")
    _map_filter_args(ex)
    im = command(sub, "import", "validate tile files and copy them into a store")
    im.add_argument("sources", type=Path, nargs="+", help="tile files or directories")
    im.add_argument("--into", required=True, metavar="STORE",
                    help="destination store: " + STORE_HELP)
    im.add_argument("--on-conflict", choices=["skip", "overwrite", "newer"], default="skip",
                    help="when the store has the tile already: keep it, replace it, or "
                         "replace it by a newer stamp")
    im.add_argument("--endpoint-url", default=None, metavar="URL", help=ENDPOINT_HELP)


STORE_HELP = "a store directory, or an object store s3://bucket/prefix"
ENDPOINT_HELP = "the S3 endpoint of an s3:// store (default: the cloud's for the region)"


def _map_filter_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--endpoint-url", default=None, metavar="URL", help=ENDPOINT_HELP)
    p.add_argument("--map", default=None, help="only this map (default: any)")
    p.add_argument("--resolution", type=float, default=None, metavar="M",
                   help="only this cell size in m (default: any)")
    p.add_argument("--tile-size", type=int, default=None, metavar="CELLS",
                   help="only this tile edge in cells (default: any)")


def main(argv: Sequence[str] | None = None) -> int:
    """sogm-service tiles with these arguments."""
    from sogm_service.apps import cli

    return cli.main(["tiles", *(sys.argv[1:] if argv is None else argv)])


def run_tiles(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run a parsed ``tiles`` command: 0 = success, 1 = bad or rejected files listed,
    2 = refused (one line on stderr)."""
    out = sys.stdout if out is None else out
    from sogm_service.apps.tileimport import cmd_import

    handler = {"ls": cmd_ls, "export": cmd_export, "import": cmd_import}[args.tiles_command]
    try:
        return handler(args, out)
    except (UsageError, StoreLockedError, StoreUnavailableError, ConfigError) as exc:
        words = getattr(args, "command_words", f"tiles {args.tiles_command}")
        return fail(words, str(exc))
    except Exception as exc:
        from sogm_service.store.s3objects import error_code

        if error_code(exc) is None:  # not the object store's refusal (no such bucket, ...)
            raise
        return fail(getattr(args, "command_words", f"tiles {args.tiles_command}"), str(exc))


# -- scanning -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One ``*.tile`` file of a directory: its header, or why it is unusable."""

    path: PurePath
    header: TileHeader | None
    size: int
    problem: str | None

    @property
    def key(self) -> MapKey | None:
        h = self.header
        return None if h is None else (h.map_name, h.resolution, h.tile_size)


def scan(directory: str | Path, verify: bool = False,
         endpoint_url: str | None = None) -> list[Entry]:
    """Read every tile header in a store (``verify``: the whole file)."""
    if is_url(directory):
        return _scan_objects(str(directory), verify, endpoint_url)
    directory = Path(directory)
    if not directory.is_dir():
        raise UsageError(f"{directory} is not a directory")
    entries = []
    for path in sorted(directory.glob(f"*{SUFFIX}")):
        try:
            if verify:
                header = read_tile_file(path).header
                size = path.stat().st_size
            else:
                header, size = read_tile_header(path)
            entries.append(Entry(path, header, size, None))
        except (TileFormatError, OSError) as exc:
            reason = exc.reason if isinstance(exc, TileFormatError) else str(exc)
            entries.append(Entry(path, None, _size(path), reason))
    return entries


def _scan_objects(url: str, verify: bool, endpoint_url: str | None) -> list[Entry]:
    """Every tile object under an s3:// prefix: its header (one ranged GET), or all of it."""
    from sogm_service.store.s3objects import S3Location, S3Objects, s3_client

    location = S3Location.parse(url)
    objects = S3Objects(location, s3_client(endpoint_url))
    entries = []
    try:
        for key, size, _ in objects.list():
            where = location.where(key)
            try:
                if verify:
                    got = objects.get(key)
                    header = None if got is None else tile_from_bytes(got[0]).header
                else:
                    head = objects.header(key)
                    header = None if head is None else head[0]
                    if head is not None and head[1] != size:
                        raise TileFormatError(f"object is {size} bytes, header says {head[1]}")
                if header is not None:
                    entries.append(Entry(where, header, size, None))
            except TileFormatError as exc:
                entries.append(Entry(where, None, size, exc.reason))
    except Exception as exc:
        if isinstance(exc, TileFormatError | ConfigError):
            raise
        raise UsageError(f"cannot list {url}: {exc}") from None
    return entries


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _matches(entry: Entry, args: argparse.Namespace) -> bool:
    h = entry.header
    if h is None:
        return True
    return ((args.map is None or h.map_name == args.map)
            and (args.resolution is None or math.isclose(h.resolution, args.resolution))
            and (args.tile_size is None or h.tile_size == args.tile_size))


# -- ls -------------------------------------------------------------------------------------
def cmd_ls(args: argparse.Namespace, out: TextIO) -> int:
    entries = [e for e in scan(args.directory, args.verify, args.endpoint_url)
               if _matches(e, args)]
    print(f"{'map':<12} {'res':>6} {'T':>5} {'i':>6} {'j':>6} {'layers':<28} {'bytes':>9} "
          f"{'stamp (UTC)':<23} file", file=out)
    for e in entries:
        print(_ls_line(e), file=out)
    bad = sum(e.problem is not None for e in entries)
    print(f"{len(entries) - bad} tile(s), {bad} bad", file=out)
    return 1 if bad else 0


def _ls_line(e: Entry) -> str:
    if e.header is None:
        return f"BAD {e.path.name}: {e.problem}"
    h = e.header
    layers = f"{len(h.layers)}: {','.join(h.layers)}"
    if len(layers) > 28:
        layers = layers[:27] + "…"
    return (f"{h.map_name:<12} {h.resolution:>6.3f} {h.tile_size:>5} {h.i:>6} {h.j:>6} "
            f"{layers:<28} {e.size:>9} {_iso(h.stamp):<23} {e.path.name}")


def _iso(stamp: float) -> str:
    try:
        return datetime.fromtimestamp(stamp, UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:23]
    except (OverflowError, OSError, ValueError):
        return f"{stamp:.3f}"


# -- export ---------------------------------------------------------------------------------
@dataclass
class Region:
    """A mosaic of tiles: ``(N, H, W)`` log-odds whose cell (0, 0) corner is ``origin``."""

    layers: list[str]
    data: npt.NDArray[np.int16]
    origin: tuple[float, float]
    resolution: float


def cmd_export(args: argparse.Namespace, out: TextIO) -> int:
    entries = [e for e in scan(args.directory, endpoint_url=args.endpoint_url)
               if _matches(e, args) and e.header is not None]
    key = _single_map(entries)
    store = open_readonly(args.directory, key, args.endpoint_url)
    lattice = TileLattice(key[1], key[2])
    region = _export_region(store, lattice, args)
    if args.layers:
        region = _select_layers(region, args.layers.split(","))
    written = _write_export(region, args.out, args.scale)
    for path in written:
        print(f"wrote {path}", file=out)
    for problem in store.problems:
        print(f"skipped {problem.path.name}: {problem.reason}", file=out)
    return 1 if store.problems else 0


def _single_map(entries: list[Entry]) -> MapKey:
    keys = sorted({e.key for e in entries if e.key is not None})
    if not keys:
        raise UsageError("no matching tiles in the directory")
    if len(keys) > 1:
        listed = ", ".join(f"{m} r={r} T={t}" for m, r, t in keys)
        raise UsageError(f"several maps here ({listed}); choose with --map/--resolution/"
                        "--tile-size")
    return keys[0]


def _export_region(store: TileStore, lattice: TileLattice, args: argparse.Namespace) -> Region:
    if args.tile is not None:
        i, j = args.tile
        return mosaic(store, lattice, i, j, i, j)
    if args.range is not None:
        i0, j0, i1, j1 = args.range
        return mosaic(store, lattice, min(i0, i1), min(j0, j1), max(i0, i1), max(j0, j1))
    return box_region(store, lattice, *args.box)


def mosaic(store: TileStore, lattice: TileLattice, i0: int, j0: int, i1: int,
           j1: int) -> Region:
    """Tiles ``i0..i1 x j0..j1`` side by side; missing tiles and layers stay unknown (0)."""
    t = lattice.tile_size
    w, h = (i1 - i0 + 1) * t, (j1 - j0 + 1) * t
    if w * h > MAX_EXPORT_CELLS:
        raise UsageError(f"region of {w}x{h} cells is larger than {MAX_EXPORT_CELLS} per layer")
    tiles = _load_tiles(store, [(i, j) for j in range(j0, j1 + 1) for i in range(i0, i1 + 1)])
    if not tiles:
        raise UsageError(f"no readable tile in i {i0}..{i1}, j {j0}..{j1}")
    layers = _union_layers(tile.header.layers for tile in tiles)
    data = np.zeros((len(layers), h, w), dtype=np.int16)
    for tile in tiles:
        u, v = (tile.header.i - i0) * t, (tile.header.j - j0) * t
        for k, name in enumerate(tile.header.layers):
            data[layers.index(name), v:v + t, u:u + t] = tile.data[k]
    origin = lattice.tile_origin(i0, j0)
    return Region(layers, data, (origin.x, origin.y), lattice.resolution)


def _load_tiles(store: TileStore, indices: list[TileIndex]) -> list[StoredTile]:
    from tqdm import tqdm

    tiles = []
    for i, j in tqdm(indices, desc="tiles export", unit="tile", file=sys.stderr, disable=None,
                     leave=False):
        tile = store.load(i, j)
        if tile is not None:
            tiles.append(tile)
    return tiles


def _union_layers(names: Iterable[tuple[str, ...]]) -> list[str]:
    out: list[str] = []
    for group in names:
        out.extend(n for n in group if n not in out)
    return out


def box_region(store: TileStore, lattice: TileLattice, xmin: float, ymin: float, xmax: float,
               ymax: float) -> Region:
    """The cells meeting the metric box ``[xmin, xmax] x [ymin, ymax]``."""
    if not (xmax > xmin and ymax > ymin):
        raise UsageError("the box needs XMIN < XMAX and YMIN < YMAX")
    (i0, j0), (i1, j1) = lattice.tile_of(xmin, ymin), lattice.tile_of(xmax, ymax)
    full = mosaic(store, lattice, i0, j0, i1, j1)
    res = lattice.resolution
    # The tolerance keeps 0.3 / 0.1 = 2.9999999999999996 from grabbing one more cell.
    u0 = math.floor((xmin - full.origin[0]) / res + _CELL_EPS)
    v0 = math.floor((ymin - full.origin[1]) / res + _CELL_EPS)
    u1 = math.ceil((xmax - full.origin[0]) / res - _CELL_EPS)
    v1 = math.ceil((ymax - full.origin[1]) / res - _CELL_EPS)
    data = full.data[:, v0:v1, u0:u1]
    return Region(full.layers, np.ascontiguousarray(data),
                  (full.origin[0] + u0 * res, full.origin[1] + v0 * res), res)


def _select_layers(region: Region, names: list[str]) -> Region:
    missing = [n for n in names if n not in region.layers]
    if missing:
        raise UsageError(f"no layer {missing} here; layers are {region.layers}")
    idx = [region.layers.index(n) for n in names]
    return Region(names, region.data[idx], region.origin, region.resolution)


def _write_export(region: Region, out: Path, scale: int) -> list[Path]:
    suffix = out.suffix.lower()
    if suffix == ".npy":
        return _write_npy(region, out)
    if suffix == ".png":
        return _write_pngs(region, out, max(1, scale))
    raise UsageError(f"--out must end with .png or .npy, got {out.name}")


def _write_npy(region: Region, out: Path) -> list[Path]:
    np.save(out, region.data)
    side = out.with_name(out.name + ".json")
    side.write_text(json.dumps({
        "layers": region.layers, "shape": list(region.data.shape), "dtype": "int16",
        "units": f"log-odds, {logodds.SCALE:g} per nat, 0 = unknown",
        "resolution": region.resolution, "origin": list(region.origin),
        "axes": "[layer, row (y up from origin), column (x)]"}, indent=2) + "\n")
    return [out, side]


def _write_pngs(region: Region, out: Path, scale: int) -> list[Path]:
    import cv2  # heavy; only export needs it

    from sogm_service.apps.render import probability_image

    written: list[Path] = []
    used: set[str] = set()
    for k, name in enumerate(region.layers):
        stem = _safe(name)
        if stem in used:
            stem = f"{stem}_{k}"
        used.add(stem)
        path = out.with_name(f"{out.stem}_{stem}.png")
        layer = region.data[k]
        img = probability_image(logodds.fixed_to_prob(layer), unknown=layer == 0, scale=scale)
        if not cv2.imwrite(os.fspath(path), img):
            raise UsageError(f"could not write {path}")
        written.append(path)
    return written


def _safe(name: str) -> str:
    """A layer name as a file-name fragment (``robot1/laser/obstacle`` -> ``robot1-laser-...``)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-.") or "layer"
