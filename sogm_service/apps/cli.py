"""The sogm-service command: one argparse tree assembled from the app modules.

Each module in `MODULES` registers its subcommands (`add_parser(subparsers)`, with a handler
set as the parser's default); this module only assembles the tree, sets up logging from the
common options (-v, -q, --log-level, accepted before or after any subcommand) and dispatches.
Heavy modules (zenoh sessions, numba kernels, the simulator) are imported by the handlers, and
only the module of the command being run is loaded at all, so serve starts fast.

Every mistake a person can make (no server, a bad endpoint, a file that is not a grid, a store
in use, a config that does not validate, an ISM the server rejects, a missing optional extra)
ends in one line on stderr, prefixed "sogm-service:", and exit status 2, never a traceback; a
closed output pipe (| head) ends quietly with status 141.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from sogm_service.apps.logs import setup_logging
from sogm_service.apps.options import (
    EXIT_USAGE,
    EXTRA_OF_MODULE,
    PROG,
    HelpFormatter,
    MissingExtraError,
    Parser,
    UsageError,
    fail,
    log_options,
    one_line,
)
from sogm_service.wire.errors import ClientError, SogmError

MODULES: dict[str, str] = {
    "serve": "sogm_service.apps.serve",
    "router": "sogm_service.apps.serve",
    "query": "sogm_service.apps.query",
    "publish-ism": "sogm_service.apps.publish",
    "schemas": "sogm_service.apps.publish",
    "tiles": "sogm_service.apps.tiletool",
    "layers": "sogm_service.apps.layers",
    "replay": "sogm_service.apps.replay",
    "demo": "sogm_service.apps.demo",
    "view": "sogm_service.apps.viewer",
    "certs": "sogm_service.apps.certs",
    "export": "sogm_service.apps.nav2tool",
    "import": "sogm_service.apps.nav2tool",
    "eval": "sogm_service.apps.labs",
    "bench": "sogm_service.apps.labs",
}
"""Each subcommand and the module that registers it (in the order of the help)."""

# Processes that fuse or sample for long: their large temporaries are kept on the heap
# (sogm_service.service.server.allocator), which the short-lived commands do not need.
_LONG_RUNNING = frozenset({"serve", "demo", "replay", "bench"})
CLOSED_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a writer whose reader left


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sogm-service")
    except PackageNotFoundError:
        return "unknown"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command tree; ``only``: just that subcommand's module (the one about to run), else
    every module (the top-level help lists them all)."""
    parser = Parser(
        prog=PROG, formatter_class=HelpFormatter,
        description="Semantical occupancy grid map server on Zenoh.",
        epilog="Every command takes -v/-q/--log-level; 'sogm-service COMMAND -h' for its "
               "options.  Mistakes end with one line on stderr and exit status 2.")
    log_options(parser)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    names = [MODULES[only]] if only in MODULES else list(dict.fromkeys(MODULES.values()))
    for name in names:
        importlib.import_module(name).add_parser(sub)
    return parser


def _command_of(argv: list[str]) -> str | None:
    """The subcommand's name (after global logging options), if any."""
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in ("-v", "--verbose", "-q", "--quiet") or a.startswith("--log-level="):
            i += 1
        elif a == "--log-level":
            i += 2
        else:
            return None if a.startswith("-") else a
    return None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    name = _command_of(argv)
    if name in _LONG_RUNNING:
        from sogm_service.service.server.allocator import keep_large_allocations

        keep_large_allocations()
    args = build_parser(name).parse_args(argv)  # -h and usage errors: SystemExit
    setup_logging(getattr(args, "log_level", None) or "info")
    words = str(getattr(args, "command_words", name or ""))
    try:
        code = int(args.handler(args))
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's last flush
        return code
    except BrokenPipeError:
        return _closed_pipe()
    except MissingExtraError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:
        extra = EXTRA_OF_MODULE.get((exc.name or "").split(".")[0])
        if extra is None:
            raise
        print(f"{PROG}: {MissingExtraError(words, extra)}", file=sys.stderr)
        return EXIT_USAGE
    except (UsageError, SogmError, ClientError) as exc:
        return fail(words, one_line(exc))
    except KeyboardInterrupt:
        print(f"{PROG}: {words}: interrupted", file=sys.stderr)
        return 130


def _closed_pipe() -> int:
    """The reader of stdout went away: nothing more to say, and nothing to say it to (stdout
    now points at /dev/null so that the interpreter's own last flush is silent too)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real stdout (an in-process caller)
        pass
    return CLOSED_PIPE

