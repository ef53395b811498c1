"""Every key expression of the service, built and parsed in one place (architecture, section 5:
docs/architecture.md#5-the-wire).

Under ``<prefix>/<map>/`` (default ``sogm/default/``) a server declares its queryables
(:data:`QUERYABLES`), ``tiles/<i>/<j>``, ``tiles/changed``, ``robots``, the tile-event publisher
``events/tile``, scan-matching reports ``matching/<ISM key>``, the layer-drop queryable
``drop/**`` (:func:`drop_chunks`) and its liveliness token ``@server/<id>``.  ISMs and poses
arrive on their own key expressions (``ism/**``, ``pose/**`` by default): the layer is the
remainder of an ISM key after the expression's literal prefix, the robot the last chunk of a
pose key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final

DEFAULT_PREFIX: Final = "sogm"
DEFAULT_MAP: Final = "default"
DEFAULT_ISM_KEY: Final = "ism/**"
DEFAULT_POSE_KEY: Final = "pose/**"
QUERYABLES: Final = ("submap", "fused", "supercells", "info", "stats")
"""The window and status queryables every server declares under ``<prefix>/<map>/``."""


@dataclass(frozen=True)
class MapKeys:
    """The keys of one map: ``MapKeys("sogm", "default").tile(3, -2)`` ->
    ``sogm/default/tiles/3/-2``."""

    prefix: str = DEFAULT_PREFIX
    map_name: str = DEFAULT_MAP

    def key(self, *parts: str) -> str:
        """A key under ``<prefix>/<map>/``."""
        return "/".join([self.prefix.strip("/"), self.map_name, *parts])

    def tile(self, i: int, j: int) -> str:
        return self.key("tiles", str(i), str(j))

    @property
    def all_tiles(self) -> str:
        return self.key("tiles", "**")

    @property
    def tiles_changed(self) -> str:
        """The queryable that answers the tiles of a region changed since the versions a
        client holds (one reply per tile, keyed :meth:`tile`; ask with replies of any key)."""
        return self.key("tiles", "changed")

    @property
    def tile_events(self) -> str:
        return self.key("events", "tile")

    @property
    def robots(self) -> str:
        return self.key("robots")

    def server_token(self, server_id: str) -> str:
        return self.key("@server", server_id)

    @property
    def all_servers(self) -> str:
        return self.key("@server", "*")

    def member(self, server_id: str, name: str) -> str:
        """``<prefix>/<map>/member/<id>/<name>``: one cluster member's own queryable (an
        operator or the bench asking that member; which member a plain get reaches is
        Zenoh's routing choice)."""
        return self.key("member", server_id, name)

    def matching(self, ism_key: str) -> str:
        return self.key("matching", ism_key)

    @property
    def ack(self) -> str:
        """The queryable that tells what became of an ISM published with an id."""
        return self.key("ack")

    def rejections(self, robot: str) -> str:
        """Where the server reports each ISM it rejects, per robot (``*`` for all)."""
        return self.key("rejections", robot)

    def drop(self, pattern: str) -> str:
        """``<prefix>/<map>/drop/<pattern>``: the get that removes the layers matching a glob
        ``pattern`` (:func:`drop_chunks`); ``ValueError`` for a pattern no key can carry."""
        return self.key("drop", drop_chunks(pattern))

    @property
    def all_drops(self) -> str:
        """The layer-drop queryable every server declares."""
        return self.key("drop", "**")


def tile_of_key(key: str) -> tuple[int, int]:
    """``(i, j)`` of a ``.../tiles/<i>/<j>`` key; ``ValueError`` for anything else."""
    parts = key.rsplit("/", 3)
    if len(parts) != 4 or parts[1] != "tiles":
        raise ValueError(f"not a tile key: {key!r}")
    return int(parts[2]), int(parts[3])


def last_chunk(key: str) -> str:
    """The last chunk of a key: the robot of ``pose/<robot>``, the id of ``@server/<id>``."""
    return key.rsplit("/", 1)[-1]


def literal_prefix(key_expr: str) -> str:
    """The literal chunks of a key expression before its first wildcard (``ism/**`` -> ``ism``)."""
    literal = []
    for chunk in key_expr.split("/"):
        if "*" in chunk or "$" in chunk:
            break
        literal.append(chunk)
    return "/".join(literal)


def key_remainder(key: str, key_expr: str) -> str:
    """What a concrete key adds to its expression's literal prefix
    (``ism/robot1/laser/obstacle`` under ``ism/**`` -> ``robot1/laser/obstacle``)."""
    prefix = literal_prefix(key_expr)
    return key[len(prefix):].strip("/") if prefix and key.startswith(prefix) else key


def robot_of_ism_key(key: str, key_expr: str) -> str:
    """The robot an ISM key names: the first chunk after the expression's literal prefix
    (``ism/robot1/laser/obstacle`` -> ``robot1``), the chunk access control grants per robot."""
    return key_remainder(key, key_expr).split("/", 1)[0]


def ism_key(prefix: str, robot: str, sensor: str, layer: str) -> str:
    """The key a robot publishes one sensor's ISMs of one class on."""
    return f"{prefix}/{robot}/{sensor}/{layer}"


def pose_key(prefix: str, robot: str) -> str:
    return f"{prefix}/{robot}"


def is_key_chunk(chunk: str) -> bool:
    """True when ``chunk`` can be one literal chunk of a key (no wildcard, no separator)."""
    return bool(chunk) and not any(c in chunk for c in "/*$?#") and len(chunk) <= 128


DROP_PATTERN: Final = re.compile(r"^[A-Za-z0-9_\-./*\[\]!]{1,128}$")
"""A layer pattern a drop key can carry: layer-name characters, ``*`` and ``[...]``/``[!...]``
(``?`` is the selector's separator, so it cannot travel in a key)."""


def drop_chunks(pattern: str) -> str:
    """The key chunks carrying a glob ``pattern`` over layer names (``*`` crosses ``/``):
    each ``/``-chunk of the pattern is one chunk of the key, a chunk that is only ``*`` stays
    ``*`` and a ``*`` inside a chunk becomes Zenoh's ``$*`` (``robot3/*`` -> ``robot3/*``,
    ``robot*/laser`` -> ``robot$*/laser``).  So a pattern's literal first chunk (the robot
    whose layers it names) is the key's, and access control that allows a robot
    ``.../drop/<robot>/**`` allows it no pattern reaching past its own name.  ``ValueError``
    for an empty chunk or a character no key can carry."""
    collapsed = re.sub(r"\*+", "*", pattern)
    chunks = collapsed.split("/")
    if not DROP_PATTERN.match(collapsed) or not all(chunks):
        raise ValueError(f"{pattern[:140]!r} is not a layer pattern a key can carry: 1-128 "
                         "characters of [A-Za-z0-9_-./*[]!], no empty '/' chunk")
    return "/".join(c if c == "*" else c.replace("*", "$*") for c in chunks)


def drop_pattern(key: str, keys: MapKeys) -> str:
    """The glob pattern a drop key carries (the inverse of :func:`drop_chunks`; a ``**`` chunk
    reads as ``*``); ``ValueError`` when ``key`` carries none."""
    head = keys.key("drop") + "/"
    if not key.startswith(head):
        raise ValueError(f"{key[:200]!r} is not under {head!r}")
    chunks = ["*" if c == "**" else c.replace("$*", "*") for c in key[len(head):].split("/")]
    pattern = "/".join(chunks)
    if "$" in pattern or not DROP_PATTERN.match(pattern) or not all(chunks):
        raise ValueError(f"{key[len(head):][:140]!r} carries no layer pattern: 1-128 characters "
                         "of [A-Za-z0-9_-./*[]!], no empty '/' chunk")
    return pattern
