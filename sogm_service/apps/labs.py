"""sogm-service eval supercells|matching (the paper's evaluations) and sogm-service bench (the
performance suite): their options come from the eval and bench packages, their subcommands
from here, so they share the tree's logging options and one-line errors."""

from __future__ import annotations

import argparse
from typing import Any

from sogm_service.apps.options import command, subcommands


def add_parser(subparsers: Any) -> None:
    from sogm_service.bench import add_arguments as bench_arguments
    from sogm_service.bench import names as bench_names
    from sogm_service.eval.matching import add_arguments as matching_arguments
    from sogm_service.eval.segmentation import add_arguments as supercells_arguments

    ev = command(subparsers, "eval", "evaluations: eval supercells (the paper's, SEVDS vs "
                                     "SEEDS/SLIC/SLICO/LSC), eval matching (scan matching on "
                                     "the Intel log)", quiet_long=False)
    sub = subcommands(ev, "eval_what", "WHAT")
    sc = command(sub, "supercells", "SEVDS vs SEEDS/SLIC/SLICO/LSC on simulated table-top "
                                    "SOGMs: a markdown table, figures and CSV in --out")
    supercells_arguments(sc)
    sc.set_defaults(handler=_supercells)
    m = command(sub, "matching", "scan matching on a CARMEN log: acceptance against wrong "
                                 "corrections, one table row per threshold",
                quiet_long=False)  # its --quiet: no progress bar
    matching_arguments(m)
    m.set_defaults(handler=_matching)
    bench = command(subparsers, "bench", "the performance suite",
                    description="Performance suite: ratios against baselines measured in the "
                                "same run.")
    bench_arguments(bench, bench_names())
    bench.set_defaults(handler=_bench)


def _supercells(args: argparse.Namespace) -> int:
    from sogm_service.eval.segmentation import run_eval

    return run_eval(args)


def _matching(args: argparse.Namespace) -> int:
    from sogm_service.eval import matching

    return matching.run(args)


def _bench(args: argparse.Namespace) -> int:
    from sogm_service import bench
    from sogm_service.apps.certs import bench_pki

    return bench.run(args, dev_pki=bench_pki)
