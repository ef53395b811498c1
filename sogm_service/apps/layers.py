"""sogm-service layers drop PATTERN: take a robot's evidence back.

Removes every layer whose name matches the glob ``PATTERN`` (``robot3/*``; ``*`` crosses
``/``, quote it from the shell) from the map and from its store, through
:meth:`~sogm_service.client.mapclient.MapClient.drop_layers`, and prints what the server
removed.  On a secure site only the identities its access control allows may drop: a robot its
own layers (``<robot>/...``), an operator any; a denied drop gets no reply at all.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from sogm_service.apps.options import UsageError, command, connection_args, subcommands

EPILOG = ("A robot whose layers polluted the map: stop it (or fix its calibration) first, "
          "since an ISM that arrives after the drop starts its layer again.")


def add_parser(subparsers: Any) -> None:
    p = command(subparsers, "layers", "manage a running server's layers")
    sub = subcommands(p, "action", "ACTION")
    drop = command(sub, "drop", "remove the layers matching a pattern from the map and its "
                                "store", epilog=EPILOG)
    drop.add_argument("pattern", metavar="PATTERN",
                      help="glob over layer names: robot3/* (every layer of robot3), "
                           "*/camera/person; '*' crosses '/', [...] a set of characters")
    connection_args(drop, timeout="query timeout in seconds (default 30: a drop rewrites "
                                   "every stored tile that holds the layers)")
    drop.add_argument("--json", action="store_true", help="print the server's reply as JSON")
    drop.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from sogm_service.apps.query import open_client
    from sogm_service.wire.errors import QueryTimeoutError
    from sogm_service.wire.keys import drop_chunks

    try:
        drop_chunks(args.pattern)  # refused before connecting
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    args.timeout = args.timeout or 30.0
    with open_client(args) as client:
        started = time.monotonic()
        try:
            reply = client.drop_layers(args.pattern)
        except QueryTimeoutError as exc:
            raise _unanswered(client, args, exc, time.monotonic() - started) from None
    if args.json:
        print(json.dumps(reply.model_dump(mode="json"), indent=2))
        return 0
    where = "the store holds the result" if reply.stored else "no store written"
    print(f"dropped {len(reply.layers)} layer(s) matching {reply.pattern!r} on server "
          f"{reply.server_id}: {reply.tiles_rewritten} tile(s) rewritten, "
          f"{reply.tiles_removed} removed; {where}")
    for name in reply.layers:
        print(f"  {name}")
    return 0


def _unanswered(client: Any, args: argparse.Namespace, exc: Exception,
                elapsed: float) -> UsageError:
    """No reply: no server, or (a server is alive) a drop the access control denied."""
    from sogm_service.apps.query import unanswered

    if client.servers(timeout=1.0):
        return UsageError(f"no server answered the drop of {args.pattern!r} within "
                          f"{elapsed:.1f} s though one is alive: on a secure site this "
                          "identity may not drop these layers (a robot drops only its own)")
    return unanswered(client, args, exc, elapsed)
