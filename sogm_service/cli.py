"""The ``sogm-service`` command (placeholder: subcommands are added as they land)."""

from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="sogm-service")
    parser.parse_args(argv)
    return 0
