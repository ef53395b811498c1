"""Classes of layers: a glob pattern names the layers it matches, fused into one.

Wherever layers are named (the ``layers`` of a query, the client, the CLI, the ROS 2 and export
options), an entry is either a layer's exact name or a glob pattern (``*``, ``?``, ``[...]``,
matched case-sensitively by :func:`fnmatch.fnmatchcase`, where ``*`` also crosses ``/``: the
pattern ``*/laser/obstacle`` matches ``robot1/laser/obstacle`` and ``robot2/laser/obstacle``,
and ``robot3/*`` matches ``robot3/laser/obstacle``).  A pattern names a *class*: its matching
layers are independent robots' evidence about the same thing, so they are fused by the Bayesian
rule of independent evidence (the paper's Eq. 6, ``P_B``: log-odds add) into one plane, named
by the pattern.  The per-robot layers stay in the map: they are the class's provenance.

Layer names never hold glob characters (``[A-Za-z0-9_\\-./]``), so an entry is a pattern
exactly when :func:`is_pattern` says so.

Pure (numpy only, no I/O).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from fnmatch import translate

import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds

_GLOB = frozenset("*?[")


def is_pattern(name: str) -> bool:
    """Whether ``name`` holds a glob character (``*``, ``?`` or ``[``)."""
    return not _GLOB.isdisjoint(name)


@dataclass(frozen=True)
class LayerClass:
    """One plane of a reply: its ``name`` (a layer's, or the pattern's) and the map layers
    fused into it (one for an exact name, every match of a pattern, in sorted order)."""

    name: str
    members: tuple[str, ...]


class NoMatchingLayerError(LookupError):
    """Requested entries that name no layer of the map: an unknown exact name, or a pattern
    matching nothing.  ``unmatched`` holds them in the order asked."""

    def __init__(self, unmatched: Sequence[str], names: Sequence[str]) -> None:
        self.unmatched = tuple(unmatched)
        super().__init__(f"no layer matches {list(self.unmatched)}; the map has {list(names)}")


def resolve(requested: Sequence[str], names: Sequence[str], *,
            allow_empty: bool = False) -> list[LayerClass]:
    """The classes of ``requested`` over the layer ``names`` (one per entry, in order).

    An exact name gives ``LayerClass(name, (name,))``; a pattern gives
    ``LayerClass(pattern, matches)`` with every matching name, sorted.  An entry that matches
    nothing raises :class:`NoMatchingLayerError` listing every such entry (queries refuse it with
    ``unknown_layer``), unless ``allow_empty``: then it is a class without members, whose plane
    is unknown everywhere (for a standing subscription whose robots have not yet written).
    """
    present = set(names)
    ordered = sorted(present)
    classes: list[LayerClass] = []
    unmatched: list[str] = []
    seen: dict[str, tuple[str, ...]] = {}  # an entry asked twice is matched once
    for entry in requested:
        members = seen.get(entry)
        if members is None:
            members = seen[entry] = _members(entry, ordered, present)
        if not members:
            unmatched.append(entry)
        classes.append(LayerClass(entry, members))
    if unmatched and not allow_empty:
        raise NoMatchingLayerError(unmatched, list(names))
    return classes


def _members(entry: str, ordered: list[str], present: set[str]) -> tuple[str, ...]:
    if not is_pattern(entry):
        return (entry,) if entry in present else ()
    match = re.compile(translate(entry)).match  # fnmatchcase's rule, compiled once per entry
    return tuple(n for n in ordered if match(n))


def member_layers(classes: Sequence[LayerClass]) -> list[str]:
    """The distinct layers the classes read, in first-use order: what to sample once."""
    return list(dict.fromkeys(m for c in classes for m in c.members))


def fuse_classes(stack: npt.NDArray[np.int16], names: Sequence[str],
                 classes: Sequence[LayerClass], *,
                 limits: tuple[int, int] | None = None) -> npt.NDArray[np.int16]:
    """``(len(classes), H, W)`` int16 fixed log-odds: each class's members fused.

    ``stack`` is ``(len(names), H, W)`` as :meth:`TiledMap.sample
    <sogm_service.core.map.reading.Reading.sample>` returns it (int16 fixed log-odds, 0 where
    unknown), plane ``k`` the layer ``names[k]``.  A class's plane is the sum of its members'
    log-odds (Bayesian fusion of independent evidence: where only one robot saw a cell it is
    that robot's value, where none did it stays 0), clamped as the map clamps a cell
    (``limits`` from :func:`~sogm_service.core.logodds.clamp_limits`, default the map's
    default ``eps0``).  A class of one layer is that layer's plane unchanged; a class without
    members is unknown (0).  Raises ``KeyError`` for a member not in ``names``.
    """
    if stack.ndim != 3 or stack.shape[0] != len(names):
        raise ValueError(f"stack {stack.shape} does not hold one plane per name "
                         f"({len(names)} names)")
    lo, hi = logodds.clamp_limits() if limits is None else limits
    index = {n: k for k, n in enumerate(names)}
    out = np.zeros((len(classes), *stack.shape[1:]), dtype=np.int16)
    for c, cls in enumerate(classes):
        ids = [index[m] for m in cls.members]
        if len(ids) == 1:
            out[c] = stack[ids[0]]
        elif ids:
            total = np.sum(stack[ids], axis=0, dtype=np.int32)
            out[c] = np.clip(total, lo, hi)
    return out
