"""A development PKI for a secure site: ``sogm-service certs init|add|show``.

It writes, into one directory,

- ``ca.crt`` / ``ca.key``: a site certificate authority (EC P-256, self-signed);
- ``<name>.crt`` / ``<name>.key``: one certificate and key per identity (server, router, robot,
  viewer), common name = the name, subject alternative names ``localhost``, ``127.0.0.1`` and
  any extra ``--san``; usable for both ends of a TLS link (server and client authentication);
- ``<name>.json5``: a ready Zenoh configuration per identity, with absolute paths, mutual TLS
  (``transport/link/tls`` with ``enable_mtls``), multicast scouting off, the mode and endpoint of
  the identity's role, and -- on the node everyone connects to (the first server, or the router
  when there is one) -- the ``access_control`` rules below, keyed by certificate common name;
- ``pki.json``: the manifest (roles, endpoint, map, prefix, extra SANs) that ``certs add`` reads
  to issue a new identity with the same CA and to rewrite the access-control configs.

Topology.  Without a router the first server is a Zenoh *peer* listening on the endpoint, and
everyone else (further servers, robots, viewers) connects to it.  With ``--router NAME`` the
router (mode ``router``) listens on the endpoint and carries the access control; servers, robots
and viewers are *clients* of it (a client opens no listener, so nothing reaches a server except
through the router's checks).

Access control (default deny, by certificate common name, on the listening node):

- a robot ``R`` may put only on ``ism/R/**`` and ``pose/R``; may query
  ``<prefix>/<map>/{submap,fused,supercells,info,stats,robots}``; may subscribe to
  ``<prefix>/<map>/events/**`` and ``<prefix>/<map>/rejections/R``; may look up and watch the
  servers' liveliness tokens ``<prefix>/<map>/@server/*``;
- a robot ``R`` may also drop its own layers: query ``<prefix>/<map>/drop/R/**`` (the drop key
  carries the layer pattern, so a pattern reaching past ``R/`` is another key, denied);
- a viewer may do the same queries, event subscriptions and liveliness look-ups, and subscribe
  to ``pose/**``; it may put, delete, declare or reply nothing;
- an operator may do what a viewer may, and drop any layers: query ``<prefix>/<map>/drop/**``;
- server (and router) identities may do everything: they are the only ones that may declare
  queryables, publish under ``<prefix>/<map>/**``, hold ``<prefix>/<map>/@server/*`` tokens and
  read ``<prefix>/<map>/tiles/**``;
- anything not listed is refused, in both directions (ingress rules say what an identity may
  send, egress rules what it may receive).

This is a development and test PKI: the CA key sits next to the certificates, unencrypted (mode
0600).  With a real PKI, give the Zenoh configs your own CA, certificates and keys (the templates
in ``deploy/secure/`` show every field) and keep the access-control rules keyed by the common
names your CA issues.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cryptography import x509

from sogm_service.apps.options import command, fail, subcommands
from sogm_service.apps.pki import (
    DEFAULT_DAYS,
    DEFAULT_ENDPOINT,
    MANIFEST,
    READ_QUERIES,
    CertificateAuthority,
    Pki,
    PkiError,
    _check_endpoint,
    _check_map,
    _check_name,
    _check_san,
    _write_public,
    load_ca,
    make_ca,
    make_identity,
    write_cert,
    write_key,
)
from sogm_service.wire.keys import QUERYABLES

# --------------------------------------------------------------------------- access control

def access_control(pki: Pki) -> dict[str, Any]:
    """The ``access_control`` section for the node everyone connects to (see module doc)."""
    base = f"{pki.prefix.strip('/')}/{pki.map_name}"
    # The read queries, also as asked of one cluster member (``member/<id>/<name>``).
    reads = [f"{base}/{q}" for q in READ_QUERIES] + \
        [f"{base}/member/*/{q}" for q in QUERYABLES]
    events = f"{base}/events/**"
    drops = f"{base}/drop"
    servers_token = f"{base}/@server/*"
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def rule(rid: str, flow: str, messages: list[str], keys: list[str]) -> str:
        rules.append({"id": rid, "permission": "allow", "flows": [flow],
                      "messages": messages, "key_exprs": keys})
        return rid

    trusted = [*pki.servers, *([pki.router] if pki.router else [])]
    every = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
             "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
    # ``**`` does not match a verbatim chunk such as ``@server``: name the tokens' keys too.
    rule("trusted-in", "ingress", every, ["**", servers_token])
    rule("trusted-out", "egress", every, ["**", servers_token])
    subjects.append({"id": "servers", "cert_common_names": trusted})
    policies.append({"id": "servers", "rules": ["trusted-in", "trusted-out"],
                     "subjects": ["servers"]})

    # What robots and viewers share: read queries and their replies, events, server discovery.
    rule("read-query", "ingress", ["query"], reads)
    rule("read-reply", "egress", ["reply"], reads)
    rule("events-sub", "ingress", ["declare_subscriber"], [events])
    rule("events-put", "egress", ["put"], [events])
    rule("discover-in", "ingress", ["liveliness_query", "declare_liveliness_subscriber"],
         [servers_token])
    rule("discover-out", "egress", ["liveliness_token"], [servers_token])
    # Let clients know the servers' queryables (never tiles/**) ...
    rule("read-decl", "egress", ["declare_queryable"], reads)
    shared = ["read-query", "read-reply", "read-decl", "events-sub", "events-put",
              "discover-in", "discover-out"]
    # ... and, for robots, the servers' subscriptions: a client's declared publisher sends
    # only when it knows a matching subscriber (without this, MapClient.publish_ism's puts
    # are dropped at the robot). It tells the robot that someone listens, nothing more.
    rule("ingest-decl", "egress", ["declare_subscriber"], ["ism/**", "pose/**"])
    if pki.robots or pki.operators:  # those who may drop learn of the servers' drop queryable
        rule("drop-decl", "egress", ["declare_queryable"], [f"{drops}/**"])

    for robot in pki.robots:
        own = [rule(f"robot-{robot}-put", "ingress", ["put"], [f"ism/{robot}/**",
                                                               f"pose/{robot}"]),
               rule(f"robot-{robot}-rej-sub", "ingress", ["declare_subscriber"],
                    [f"{base}/rejections/{robot}"]),
               rule(f"robot-{robot}-rej-put", "egress", ["put"],
                    [f"{base}/rejections/{robot}"]),
               rule(f"robot-{robot}-drop", "ingress", ["query"], [f"{drops}/{robot}/**"]),
               rule(f"robot-{robot}-drop-reply", "egress", ["reply"], [f"{drops}/{robot}/**"])]
        subjects.append({"id": f"robot-{robot}", "cert_common_names": [robot]})
        policies.append({"id": f"robot-{robot}", "rules": [*shared, "ingest-decl", "drop-decl",
                                                           *own],
                         "subjects": [f"robot-{robot}"]})

    if pki.viewers or pki.operators:
        rule("viewer-pose-sub", "ingress", ["declare_subscriber"], ["pose/**"])
        rule("viewer-pose-put", "egress", ["put"], ["pose/**"])
    if pki.viewers:
        subjects.append({"id": "viewers", "cert_common_names": list(pki.viewers)})
        policies.append({"id": "viewers",
                         "rules": [*shared, "viewer-pose-sub", "viewer-pose-put"],
                         "subjects": ["viewers"]})
    if pki.operators:
        rule("operator-drop", "ingress", ["query"], [f"{drops}/**"])
        rule("operator-drop-reply", "egress", ["reply"], [f"{drops}/**"])
        subjects.append({"id": "operators", "cert_common_names": list(pki.operators)})
        policies.append({"id": "operators",
                         "rules": [*shared, "viewer-pose-sub", "viewer-pose-put", "drop-decl",
                                   "operator-drop", "operator-drop-reply"],
                         "subjects": ["operators"]})

    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


# --------------------------------------------------------------------------- zenoh configs

def zenoh_config(pki: Pki, name: str) -> dict[str, Any]:
    """The Zenoh configuration (as a dict) of identity ``name``."""
    role = pki.role(name)
    tls = {
        "root_ca_certificate": str(pki.ca_cert),
        "listen_certificate": str(pki.cert(name)),
        "listen_private_key": str(pki.key(name)),
        "connect_certificate": str(pki.cert(name)),
        "connect_private_key": str(pki.key(name)),
        "enable_mtls": True,
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }
    listens = name == pki.acl_holder
    if role == "router":
        mode = "router"
    elif role == "server" and not pki.router:
        mode = "peer"
    else:
        mode = "client"
    config: dict[str, Any] = {
        "mode": mode,
        "listen": {"endpoints": [pki.endpoint] if listens else []},
        "connect": {"endpoints": [] if listens else [pki.endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"], "tls": tls}},
    }
    if listens:
        config["access_control"] = access_control(pki)
    return config


def _config_text(pki: Pki, name: str) -> str:
    role = pki.role(name)
    holder = pki.acl_holder
    lines = [
        f"// Zenoh config of {role} {name!r} (written by `sogm-service certs`; regenerate rather",
        "// than edit: `certs add` rewrites the access-control rules).",
        f"// Mutual TLS with the site CA {pki.ca_cert}.",
    ]
    if name == holder:
        lines.append(f"// Listens on {pki.endpoint} and enforces the site's access control.")
    else:
        lines.append(f"// Connects to {holder!r} at {pki.endpoint}.")
    return "\n".join(lines) + "\n" + json.dumps(zenoh_config(pki, name), indent=2) + "\n"


def write_configs(pki: Pki) -> None:
    """(Re)write every identity's JSON5 config and the manifest."""
    for name in pki.names():
        _write_public(pki.config(name), _config_text(pki, name).encode())
    _write_public(pki.directory / MANIFEST, (json.dumps(pki.to_json(), indent=2) + "\n").encode())


def _issue(pki: Pki, ca: CertificateAuthority, name: str) -> None:
    cert, key = make_identity(ca, name, sans=pki.sans, days=pki.days)
    write_key(pki.key(name), key)
    write_cert(pki.cert(name), cert)


# --------------------------------------------------------------------------- public API

def init_pki(directory: Path | str, *, server_names: Sequence[str],
             robot_names: Sequence[str] = (), viewer_names: Sequence[str] = (),
             router_name: str | None = None, endpoint: str = DEFAULT_ENDPOINT,
             sans: Sequence[str] = (), map_name: str = "default", prefix: str = "sogm",
             days: int = DEFAULT_DAYS, force: bool = False,
             operator_names: Sequence[str] = ()) -> Pki:
    """Create a CA, one certificate/key/Zenoh config per identity and the manifest.

    Refuses (``PkiError``) an existing PKI unless ``force``, a bad or duplicate name, no
    server, or a non-TLS endpoint.
    """
    directory = Path(directory).resolve()
    if not server_names:
        raise PkiError("no_server", "at least one server identity is needed")
    names = [*server_names, *([router_name] if router_name else []), *robot_names,
             *viewer_names, *operator_names]
    for n in names:
        _check_name(n)
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise PkiError("duplicate_name", f"identities named more than once: {dupes}")
    _check_endpoint(endpoint)
    for san in sans:
        _check_san(san)
    _check_map(map_name, prefix)
    if days <= 0:
        raise PkiError("bad_days", f"days must be positive, not {days}")
    if (directory / "ca.key").exists() and not force:
        raise PkiError("exists", f"{directory} already holds a CA (use `certs add`, or --force "
                                 "to start over)")
    directory.mkdir(parents=True, exist_ok=True)
    pki = Pki(directory, list(server_names), list(robot_names), list(viewer_names), router_name,
              endpoint, list(sans), map_name, prefix, days, list(operator_names))
    ca = make_ca()
    write_key(directory / "ca.key", ca.key)
    write_cert(pki.ca_cert, ca.cert)
    for n in names:
        _issue(pki, ca, n)
    write_configs(pki)
    return pki


@contextmanager
def bench_pki() -> Iterator[tuple[Path, Path]]:
    """``sogm-service bench --secure``: a fresh dev PKI in a temporary directory (removed
    afterwards): the configs of one robot, ``bench``, and of the server."""
    with tempfile.TemporaryDirectory(prefix="sogm-bench-pki-") as tmp:
        pki = init_pki(tmp, server_names=["server"], robot_names=["bench"],
                       endpoint="tls/127.0.0.1:7447")
        yield pki.config("bench"), pki.config("server")


def add_identity(directory: Path | str, name: str, role: str = "robot") -> Pki:
    """Issue a new robot, viewer, operator or server with the existing CA; rewrite every
    config so the access control (on the router, or the first server) knows it.  Nodes that
    carry the access control must be restarted to load it."""
    pki = Pki.load(Path(directory))
    _check_name(name)
    if name in pki.names():
        raise PkiError("duplicate_name", f"{name!r} already exists in {pki.directory}")
    if role == "robot":
        pki.robots.append(name)
    elif role == "viewer":
        pki.viewers.append(name)
    elif role == "server":
        pki.servers.append(name)
    elif role == "operator":
        pki.operators.append(name)
    else:
        raise PkiError("bad_role", f"{role!r}: one of robot, viewer, operator, server")
    _issue(pki, load_ca(pki.directory), name)
    write_configs(pki)
    return pki


def renew_identity(directory: Path | str, name: str, days: int | None = None) -> Pki:
    """A new key and certificate for ``name`` (rotation); its config stays the same."""
    pki = Pki.load(Path(directory))
    if name not in pki.names():
        raise PkiError("unknown_name", f"{name!r} is not an identity of {pki.directory}")
    if days is not None:
        if days <= 0:
            raise PkiError("bad_days", f"days must be positive, not {days}")
        pki.days = days
    _issue(pki, load_ca(pki.directory), name)
    write_configs(pki)
    return pki


def remove_identity(directory: Path | str, name: str) -> Pki:
    """Drop ``name`` from the site: delete its key, certificate and config and rewrite the
    access control without it (restart the node that carries it).  Its certificate still
    passes mutual TLS until it expires, but its common name matches no rule: default deny.
    Never reissue a removed name while its old certificate is valid (the rules are by name)."""
    pki = Pki.load(Path(directory))
    if name not in pki.names():
        raise PkiError("unknown_name", f"{name!r} is not an identity of {pki.directory}")
    if name == pki.router or pki.servers == [name]:
        raise PkiError("needed", f"{name!r} is the router or the only server")
    for lst in (pki.servers, pki.robots, pki.viewers, pki.operators):
        if name in lst:
            lst.remove(name)
    for path in (pki.key(name), pki.cert(name), pki.config(name)):
        path.unlink(missing_ok=True)
    write_configs(pki)
    return pki


def add_parser(subparsers: Any) -> None:
    p = command(subparsers, "certs", "a dev PKI and mutual-TLS / access-control Zenoh configs",
                description="A development PKI and Zenoh mutual-TLS/access-control configs for "
                            "a site: a CA, one certificate, key and Zenoh config per identity, "
                            "access control by certificate name on the listening node.")
    p.set_defaults(handler=run)
    sub = subcommands(p, "action", "ACTION")
    init = command(sub, "init", "create a CA, identities and their Zenoh configs")
    init.add_argument("dir", type=Path, help="directory to write (created)")
    init.add_argument("--server", action="append", required=True, metavar="NAME",
                      help="a map server identity (repeatable; the first listens when there "
                           "is no router)")
    init.add_argument("--robot", action="append", default=[], metavar="NAME",
                      help="a robot identity (repeatable; default: none)")
    init.add_argument("--viewer", action="append", default=[], metavar="NAME",
                      help="a read-only viewer identity (repeatable; default: none)")
    init.add_argument("--operator", action="append", default=[], metavar="NAME",
                      help="a viewer that may also drop any layers (`layers drop`; "
                           "repeatable; default: none)")
    init.add_argument("--router", default=None, metavar="NAME",
                      help="a router in the middle: it listens and enforces access control "
                           "(default: none, the first server listens)")
    init.add_argument("--endpoint", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                      help="the listening TLS endpoint")
    init.add_argument("--san", action="append", default=[], metavar="HOST",
                      help="extra subject alternative name (DNS name or IP; repeatable; "
                           "default: none beyond localhost and 127.0.0.1)")
    init.add_argument("--map", default="default", help="map name")
    init.add_argument("--prefix", default="sogm", help="key prefix")
    init.add_argument("--days", type=int, default=DEFAULT_DAYS, metavar="DAYS",
                      help="validity of the identities' certificates (days)")
    init.add_argument("--force", action="store_true", help="overwrite an existing PKI")
    add = command(sub, "add", "issue one more identity with the existing CA")
    add.add_argument("dir", type=Path, help="the PKI directory")
    who = add.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", metavar="NAME", help="a robot identity")
    who.add_argument("--viewer", metavar="NAME", help="a read-only viewer identity")
    who.add_argument("--server", metavar="NAME", help="one more map server identity")
    who.add_argument("--operator", metavar="NAME", help="a viewer that may drop layers")
    renew = command(sub, "renew", "a new key and certificate for an identity")
    renew.add_argument("dir", type=Path, help="the PKI directory")
    renew.add_argument("name", help="the identity")
    renew.add_argument("--days", type=int, default=None, metavar="DAYS",
                       help="validity of the new certificate (days; default: the PKI's)")
    remove = command(sub, "remove", "drop an identity from the site's access control")
    remove.add_argument("dir", type=Path, help="the PKI directory")
    remove.add_argument("name", help="the identity")
    show = command(sub, "show", "list the identities and their certificates' validity")
    show.add_argument("dir", type=Path, help="the PKI directory")


def _summary(pki: Pki) -> str:
    lines = [f"PKI in {pki.directory} (map {pki.map_name!r}, prefix {pki.prefix!r}, "
             f"endpoint {pki.endpoint})", f"  CA: {pki.ca_cert}"]
    for name in pki.names():
        try:
            cert = x509.load_pem_x509_certificate(pki.cert(name).read_bytes())
            until = cert.not_valid_after_utc.strftime("%Y-%m-%d %H:%M UTC")
        except (OSError, ValueError):
            until = "missing or unreadable"
        marker = "  (listens, access control)" if name == pki.acl_holder else ""
        lines.append(f"  {pki.role(name):6s} {name}: --zenoh-config {pki.config(name)}"
                     f"  valid until {until}{marker}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """sogm-service certs with these arguments; returns the exit code."""
    from sogm_service.apps import cli

    return cli.main(["certs", *(sys.argv[1:] if argv is None else argv)])


def run(args: argparse.Namespace) -> int:
    try:
        if args.action == "init":
            pki = init_pki(args.dir, server_names=args.server, robot_names=args.robot,
                           viewer_names=args.viewer, router_name=args.router,
                           endpoint=args.endpoint, sans=args.san, map_name=args.map,
                           prefix=args.prefix, days=args.days, force=args.force,
                           operator_names=args.operator)
        elif args.action == "add":
            role, name = next((r, getattr(args, r)) for r in ("robot", "viewer", "server",
                                                              "operator") if getattr(args, r))
            pki = add_identity(args.dir, name, role)
            print(f"issued {role} {name!r}; restart {pki.acl_holder!r} to load the new "
                  "access-control rules", file=sys.stderr)
        elif args.action == "renew":
            pki = renew_identity(args.dir, args.name, args.days)
        elif args.action == "remove":
            pki = remove_identity(args.dir, args.name)
            print(f"removed {args.name!r}; restart {pki.acl_holder!r} to load the new "
                  "access-control rules", file=sys.stderr)
        else:
            pki = Pki.load(args.dir)
    except PkiError as e:
        return fail(args.command_words, str(e))
    print(_summary(pki))
    return 0


if __name__ == "__main__":
    sys.exit(main())
