"""``sogm-service bench [NAMES] [--quick] [--json FILE] [--zenoh-config FILE
[--server-zenoh-config FILE] | --secure]``: the performance suite.

Every figure is a ratio against a baseline measured in the same run (medians of repeated,
interleaved runs), with the absolute numbers beside it; see ``docs/performance.md``.  This is a
benchmark, never a test: ``tests/integration/test_bench.py`` runs ``--quick`` only to keep it
working.

Modules: :mod:`.core` (rows, timing, report), :mod:`.compute` (the pure core: fusion, SEVDS,
matching), :mod:`.zbench` (through Zenoh and processes), :mod:`.procs` (helper processes),
:mod:`.transport` (the Zenoh configs of the client and server sides).
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path

from sogm_service.bench import transport
from sogm_service.bench.core import Benchmark, Row, notes, report, table, write_json

DevPki = Callable[[], AbstractContextManager[tuple[Path, Path]]]
"""Makes a fresh dev PKI for ``--secure``: (a robot's config, the server's config)."""


def registry() -> list[Benchmark]:
    """Every benchmark in report order (Zenoh ones are imported only when asked for)."""
    from sogm_service.bench import compute

    def z(name: str) -> object:
        def run(quick: bool) -> Row:
            from sogm_service.bench import zbench

            result: Row = getattr(zbench, name)(quick)
            return result
        return run

    def mixed(quick: bool) -> Row:
        from sogm_service.bench.fleet import mixed_fleet

        return mixed_fleet(quick)

    def per_robot(quick: bool) -> Row:
        from sogm_service.bench.fleet import mixed_fleet_per_robot

        return mixed_fleet_per_robot(quick)

    def flooded(quick: bool) -> Row:
        from sogm_service.bench.flood import flood

        return flood(quick)

    def clustered(quick: bool) -> Row:
        from sogm_service.bench.cluster import cluster

        return cluster(quick)

    def split(quick: bool) -> Row:
        from sogm_service.bench.cluster import cluster_split

        return cluster_split(quick)

    def scaled(quick: bool) -> Row:
        from sogm_service.bench.cluster_scale import cluster_scale

        return cluster_scale(quick)

    def gathered(quick: bool) -> Row:
        from sogm_service.bench.cluster import cluster_submap

        return cluster_submap(quick)

    def bandwidth(quick: bool) -> Row:
        from sogm_service.bench.bandwidth import bandwidth

        return bandwidth(quick)

    return [
        Benchmark("fuse_aligned", "aligned 1024x1024 prob_u8 ISM vs the streaming floor",
                  compute.fuse_aligned),
        Benchmark("fuse_rotated", "512x512 ISM at 30 deg and 1.5x res vs one footprint warp",
                  compute.fuse_rotated),
        Benchmark("submap", "256x256x4 rotated biodds submap over Zenoh vs a raw get",
                  z("submap")),  # type: ignore[arg-type]
        Benchmark("ingest", "256x256 ISMs publisher -> server vs one worker in process x cores",
                  z("ingestion")),  # type: ignore[arg-type]
        Benchmark("mixed_fleet", "sub-map p50/p99 while a fleet streams ISMs vs idle",
                  mixed),
        Benchmark("mixed_fleet_per_robot", "the same with every robot its own 4 layers "
                  "(32 layers) vs idle", per_robot),
        Benchmark("flood", "sub-map p99 while 2 publishers offer >= 2x capacity vs idle",
                  flooded),
        Benchmark("cluster", "ingestion with 2 cluster members vs 1 (replicas 1)",
                  clustered),
        Benchmark("cluster_scale", "ingestion of 1, 2, 3 members each capped at the same CPU "
                  "(replicas 1 and 2)", scaled),
        Benchmark("cluster_split", "bytes per ISM: every member gets it whole vs a split "
                  "per tile to each tile's owners", split),
        Benchmark("cluster_submap", "sub-map through a member owning none of its tiles vs "
                  "through their owner", gathered),
        Benchmark("sevds", "SEVDS 256x256x3 vs OpenCV SEEDS", compute.sevds),
        Benchmark("memory", "100 m x 100 m at 5 cm, 8 layers: peak RSS vs raw bytes",
                  z("memory")),  # type: ignore[arg-type]
        Benchmark("startup", "serve until discoverable vs import zenoh",
                  z("startup")),  # type: ignore[arg-type]
        Benchmark("matching", "scan match of a 256x256 ISM vs one ORB detect",
                  compute.matching),
        Benchmark("bandwidth", "the demo fleet's bytes on the network by class, zstd vs raw",
                  bandwidth),
    ]


def add_arguments(p: argparse.ArgumentParser, names: list[str]) -> None:
    """The options of the suite (the CLI adds them to its own subcommand)."""
    p.add_argument("names", nargs="*", metavar="NAME",
                   help=f"benchmarks to run (default all): {', '.join(names)}")
    p.add_argument("--quick", action="store_true",
                   help="few repeats, under a minute (CI smoke; numbers are rough)")
    p.add_argument("--json", metavar="FILE", default=None,
                   help="write the results here (default: none)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="open the client side's sessions (queries, publishing robots) from this "
                        "Zenoh config, honoured as is but for its endpoints (the bench's "
                        "servers listen on ephemeral ports); e.g. a robot's from "
                        "'sogm-service certs' (default: plain TCP on loopback)")
    p.add_argument("--server-zenoh-config", type=Path, default=None, metavar="FILE",
                   help="the same for the processes that stand in for the server (serve, the "
                        "raw baselines); its listen endpoint's protocol (tls) is kept "
                        "(default: plain TCP on loopback)")
    p.add_argument("--secure", action="store_true",
                   help="run through a fresh dev PKI: mutual TLS and the access control of "
                        "'sogm-service certs init' (a server and one robot)")


def run_one(bench: Benchmark, quick: bool) -> Row:
    """Run one benchmark; a crash becomes a failed row rather than ending the suite."""
    try:
        return bench.run(quick)
    except Exception as exc:
        traceback.print_exc()
        return Row(bench.name, None, None, "", None, "", False,
                   note=f"error: {type(exc).__name__}: {exc}"[:500])


def names() -> list[str]:
    return [b.name for b in registry()]


def run(args: argparse.Namespace, dev_pki: DevPki | None = None) -> int:
    """The suite as the parsed options say; the exit status."""
    benches = registry()
    by_name = {b.name: b for b in benches}
    unknown = [n for n in args.names if n not in by_name]
    if unknown:
        return _usage(f"unknown benchmark(s) {unknown}; choose from {list(by_name)}")
    if args.secure and (args.zenoh_config or args.server_zenoh_config):
        return _usage("--secure makes its own configs: give it or --zenoh-config, not both")
    if args.secure and dev_pki is None:
        return _usage("--secure needs the certs command (run it as 'sogm-service bench')")
    chosen = [by_name[n] for n in args.names] if args.names else benches
    pki = dev_pki() if args.secure and dev_pki else nullcontext(None)
    with pki as made:
        try:
            how = transport.from_files(*made) if made else \
                transport.from_files(args.zenoh_config, args.server_zenoh_config)
        except ValueError as exc:
            return _usage(str(exc))
        with transport.using(how):
            rows = _run_all(chosen, args.quick, how, args.json)
    errors = [r for r in rows if r.note.startswith("error")]
    return 1 if errors else 0


def _usage(message: str) -> int:
    print(f"sogm-service: bench: {message}", file=sys.stderr)
    return 2


def _run_all(chosen: list[Benchmark], quick: bool, how: transport.Transport,
             json_path: str | None) -> list[Row]:
    started = time.time()
    rows = []
    for bench in chosen:
        print(f"running {bench.name}: {bench.summary} ...", file=sys.stderr, flush=True)
        rows.append(run_one(bench, quick))
    print(table(rows))
    print()
    print(notes(rows))
    print(f"\nZenoh rows through: {how.describe()}")
    if json_path:
        write_json(json_path, {**report(rows, quick, started), "transport": how.describe(),
                               "transport_protocol": how.protocol,
                               "zenoh_config": str(how.client_config or ""),
                               "server_zenoh_config": str(how.server_config or "")})
    return rows
