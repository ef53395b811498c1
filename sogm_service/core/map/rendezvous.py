"""Rendezvous (highest random weight) hashing of tiles over the members of a cluster.

Every member of a map's cluster computes, from the same set of member ids, the same ``replicas``
owners of every tile: the members with the highest weights ``w(member, tile)``, a hash of both
(Thaler and Ravishankar's HRW).  No coordinator, no table to agree on: only the membership.
When a member joins, it takes over only the tiles where it now ranks among the first
``replicas`` (about ``replicas / n`` of them); when one leaves, only its tiles get a new owner,
the next member in their ranking.  The hash is BLAKE2b (stable across processes, platforms and
Python's hash randomisation).

Pure: no I/O.  The service keeps the membership (:mod:`sogm_service.service.cluster.cluster`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field

from sogm_service.core.map.tiletypes import TileIndex


def weight(member: str, index: TileIndex) -> int:
    """The weight of ``member`` for tile ``index``: 64 bits of BLAKE2b of both."""
    key = f"{index[0]},{index[1]}@{member}".encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "big")


def ranking(members: Iterable[str], index: TileIndex) -> list[str]:
    """Every member, most preferred owner of ``index`` first (ties, impossible in practice
    with 64-bit weights, broken by id so that every member ranks alike)."""
    return sorted(members, key=lambda m: (-weight(m, index), m))


def owners_of(members: Iterable[str], index: TileIndex, replicas: int) -> tuple[str, ...]:
    """The ``replicas`` owners of ``index`` (all members when there are fewer), primary first."""
    if replicas < 1:
        raise ValueError(f"replicas must be at least 1, got {replicas}")
    return tuple(ranking(members, index)[:replicas])


@dataclass(frozen=True)
class Ownership:
    """The owners of every tile under one membership (cached per tile: a map has few)."""

    members: frozenset[str]
    replicas: int
    _cache: dict[TileIndex, tuple[str, ...]] = field(default_factory=dict, compare=False,
                                                     repr=False)

    def owners(self, index: TileIndex) -> tuple[str, ...]:
        found = self._cache.get(index)
        if found is None:
            found = owners_of(self.members, index, self.replicas)
            if len(self._cache) < 1 << 20:  # bounded: a view lives until the next change
                self._cache[index] = found
        return found

    def owns(self, member: str, index: TileIndex) -> bool:
        return member in self.owners(index)

    def primary(self, index: TileIndex) -> str | None:
        found = self.owners(index)
        return found[0] if found else None

    def with_member(self, member: str) -> Ownership:
        return Ownership(self.members | {member}, self.replicas)

    def without_member(self, member: str) -> Ownership:
        return Ownership(self.members - {member}, self.replicas)
