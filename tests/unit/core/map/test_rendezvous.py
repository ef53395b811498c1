"""Rendezvous ownership of tiles (core/map/rendezvous): the same owners for any member order;
a join or a leave moves only what it must."""

from __future__ import annotations

from sogm_service.core.map.rendezvous import Ownership, owners_of, ranking


def test_owners_are_the_same_for_any_member_order_and_distinct() -> None:
    members = [f"m{k}" for k in range(5)]
    for index in [(i, j) for i in range(-5, 5) for j in range(-5, 5)]:
        a = owners_of(members, index, 2)
        b = owners_of(list(reversed(members)), index, 2)
        assert a == b and len(set(a)) == 2
    assert owners_of(["only"], (0, 0), 2) == ("only",)


def test_a_join_moves_only_tiles_to_the_new_member_and_about_its_share() -> None:
    tiles = [(i, j) for i in range(-20, 20) for j in range(-20, 20)]
    before = Ownership(frozenset({"a", "b", "c"}), 2)
    after = before.with_member("d")
    moved = 0
    for t in tiles:
        gained = set(after.owners(t)) - set(before.owners(t))
        assert gained <= {"d"}  # nobody but the newcomer gains a tile
        moved += len(gained)
    share = moved / (2 * len(tiles))  # the newcomer's fraction of all copies
    assert 0.2 < share < 0.3  # ~1/4 of the copies


def test_a_leave_reassigns_only_the_leavers_copies() -> None:
    tiles = [(i, j) for i in range(-10, 10) for j in range(-10, 10)]
    before = Ownership(frozenset({"a", "b", "c", "d"}), 2)
    after = before.without_member("b")
    for t in tiles:
        kept = set(before.owners(t)) - {"b"}
        assert kept <= set(after.owners(t)) and len(after.owners(t)) == 2
        if "b" not in before.owners(t):
            assert after.owners(t) == before.owners(t)
    assert ranking(["x", "y"], (1, 2)) == ranking(["y", "x"], (1, 2))
