"""What every subcommand of the sogm-service command shares: its parser class (one-line
errors), its help format (each default shown once), the logging options, the connection
options of a client command, the one-line refusal and the optional extras.

Each app module registers its own subcommands with `command()` and sets a handler with
`parser.set_defaults(handler=...)`; the handler takes the parsed namespace and returns the
exit status.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
from pathlib import Path
from typing import Any, NoReturn

from sogm_service.client.session import DEFAULT_ENDPOINT

EXIT_USAGE = 2
"""Exit status of every refusal: bad arguments, config, input, or what the server refused."""

PROG = "sogm-service"
LOG_LEVELS = ("debug", "info", "warning", "error")

EXTRAS: dict[str, tuple[str, ...]] = {
    "ros2": ("rosbags", "xxhash", "yaml"),
    "viewer": ("starlette", "uvicorn", "websockets"),
}
"""The optional extras whose absence ends a command (the plots extra only changes how pictures
look), by the modules they install."""

EXTRA_OF_MODULE = {module: extra for extra, modules in EXTRAS.items() for module in modules}


class UsageError(Exception):
    """A refusal the user can fix: printed as one line after the command's name, exit 2."""


class MissingExtraError(Exception):
    """A command needs an optional extra that is not installed."""

    def __init__(self, command: str, extra: str) -> None:
        super().__init__(f"{command} needs the {extra} extra: "
                         f"pip install '{PROG}[{extra}]'")


def require_extra(extra: str, command: str) -> None:
    """Refuse ``command`` (before it does anything) unless every module of ``extra`` can be
    imported.  ``find_spec`` imports nothing, and it sees a module set to None in
    ``sys.modules`` as absent, as the import system does."""
    for module in EXTRAS[extra]:
        if importlib.util.find_spec(module) is None:
            raise MissingExtraError(command, extra)


class Parser(argparse.ArgumentParser):
    """An argument parser whose mistakes end in one line (and the way to the help)."""

    def error(self, message: str) -> NoReturn:
        words = self.prog.removeprefix(PROG).strip()
        where = f"{words}: " if words else ""
        print(f"{PROG}: {where}{message} (see '{self.prog} -h')", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs kept as written; an option's default appended once, unless its
    help already says it (or there is none to say: a flag, or None explained in the text)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if ("default" in text or any(default is v for v in (None, False, argparse.SUPPRESS))
                or action.required or (not action.option_strings
                                       and action.nargs not in ("?", "*"))):
            return text
        shown = ",".join(map(str, default)) if isinstance(default, list) else default
        return f"{text} (default: {shown})".replace("%", "%%")


def log_options(p: argparse.ArgumentParser, quiet_long: bool = True) -> None:
    """-v / -q / --log-level.  SUPPRESS: given before or after the subcommand, the last wins
    and an absent one never overwrites one given earlier.  ``quiet_long``: False where the
    command's own --quiet means "no progress bar" (demo, eval matching); -q still logs less."""
    g = p.add_argument_group("logging")
    g.add_argument("-v", "--verbose", dest="log_level", action="store_const", const="debug",
                   default=argparse.SUPPRESS, help="debug logging (= --log-level debug)")
    quiet = ("-q", "--quiet") if quiet_long else ("-q",)
    g.add_argument(*quiet, dest="log_level", action="store_const", const="warning",
                   default=argparse.SUPPRESS, help="warnings and errors only")
    g.add_argument("--log-level", dest="log_level", choices=LOG_LEVELS,
                   default=argparse.SUPPRESS,
                   help="log level (default: the config's log_level for serve, else info)")


def command(subparsers: Any, name: str, help_text: str, description: str = "",
            epilog: str = "", quiet_long: bool = True) -> argparse.ArgumentParser:
    """A subcommand (at any depth) with the shared format and the logging options."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        name, help=help_text, description=description or help_text, epilog=epilog,
        formatter_class=HelpFormatter)
    log_options(p, quiet_long)
    p.set_defaults(command_words=p.prog.removeprefix(PROG).strip())  # innermost wins
    return p


def subcommands(p: argparse.ArgumentParser, dest: str, metavar: str = "COMMAND") -> Any:
    return p.add_subparsers(dest=dest, required=True, metavar=metavar)


def standalone(prog: str, description: str = "") -> argparse.ArgumentParser:
    """A parser of one command's arguments outside the tree (the demo's embedded viewer)."""
    return Parser(prog=prog, description=description, formatter_class=HelpFormatter)


def fail(command: str, message: str) -> int:
    """Print the one line of a refusal; return its exit status."""
    print(f"{PROG}: {command}: {one_line(message)}", file=sys.stderr)
    return EXIT_USAGE


def one_line(text: object) -> str:
    s = str(text).strip() or type(text).__name__
    return " ".join(s.split()) if len(s) < 2000 else s[:2000]


# -- the options of client commands ---------------------------------------------------------
def zenoh_config_arg(p: Any, what: str = "") -> None:
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE",
                   help="Zenoh JSON5 config, honoured as is (mode, TLS, endpoints), e.g. one "
                        f"written by 'sogm-service certs'{what}; replaces --connect "
                        "(default: none)")


def connection_args(p: argparse.ArgumentParser, timeout: str | None = None) -> None:
    g = p.add_argument_group("connection")
    g.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                   help="Zenoh endpoint of the server or a router (<protocol>/<host>:<port>)")
    g.add_argument("--map", default="default", help="map name")
    g.add_argument("--prefix", default="sogm", help="key prefix of the map's keys")
    g.add_argument("--timeout", type=float, default=None, metavar="S",
                   help=timeout or "query timeout in seconds (default 5, supercells 90: the "
                                   "first query after an install may wait for the server to "
                                   "compile its kernels)")
    g.add_argument("--compression", choices=["zstd", "none"], default="zstd",
                   help="zstd: ISMs sent and replies asked for compressed (10-70x fewer "
                        "bytes on the network); none: raw, for servers before schema version 3")
    zenoh_config_arg(g)


def angle_options(p: Any, what: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--yaw-deg", type=float, default=None, metavar="DEG",
                   help=f"{what} heading in degrees, counter-clockwise from the map's x axis "
                        "(default 0)")
    g.add_argument("--yaw", type=float, default=None, metavar="RAD",
                   help=f"{what} heading in radians, kept for scripts; |yaw| > 2 pi is refused "
                        "as a likely degree value: use --yaw-deg (default 0)")


def yaw(args: argparse.Namespace) -> float:
    """The heading of --yaw-deg or --yaw, in radians."""
    if args.yaw_deg is not None:
        if not math.isfinite(args.yaw_deg):
            raise UsageError("--yaw-deg must be finite")
        return math.radians(args.yaw_deg)
    value = 0.0 if args.yaw is None else float(args.yaw)
    if not math.isfinite(value) or abs(value) > 2 * math.pi + 1e-9:
        raise UsageError(f"--yaw {args.yaw} is in radians and beyond one turn: did you mean "
                         f"--yaw-deg {args.yaw}?")
    return value
