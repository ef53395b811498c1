"""The drop key: a glob pattern over layer names carried chunk by chunk, so that Zenoh's access
control (a rule allows a key expression it *includes*) grants a robot its own patterns only."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from sogm_service.wire.keys import MapKeys, drop_chunks, drop_pattern

KEYS = MapKeys("sogm", "default")
ROBOT1 = zenoh.KeyExpr("sogm/default/drop/robot1/**")  # what certs allows robot1


@pytest.mark.parametrize(("pattern", "key"), [
    ("robot2/*", "sogm/default/drop/robot2/*"),
    ("robot*/laser", "sogm/default/drop/robot$*/laser"),
    ("*/laser/obstacle", "sogm/default/drop/*/laser/obstacle"),
    ("robot[12]/x", "sogm/default/drop/robot[12]/x"),
    ("a**b", "sogm/default/drop/a$*b"),
])
def test_patterns_travel_in_the_key_and_back(pattern: str, key: str) -> None:
    assert KEYS.drop(pattern) == key
    assert drop_pattern(key, KEYS) == pattern.replace("**", "*")
    assert str(zenoh.KeyExpr(key)) == key  # a valid, canonical key expression


@pytest.mark.parametrize("pattern", ["", "a//b", "/a", "a/", "a?b", "a#b", "a$b", "x" * 129])
def test_patterns_no_key_carries_are_refused(pattern: str) -> None:
    with pytest.raises(ValueError):
        drop_chunks(pattern)


def test_keys_carrying_no_pattern_are_refused() -> None:
    for key in ("sogm/default/drop", "sogm/default/dropx/a", "sogm/default/drop/a%b",
                "sogm/other/drop/a"):
        with pytest.raises(ValueError):
            drop_pattern(key, KEYS)


CHUNK = st.text("ab1*[]!", min_size=1, max_size=6)


@given(st.lists(CHUNK, min_size=1, max_size=4))
def test_robot1_may_ask_exactly_the_patterns_under_its_literal_name(rest: list[str]) -> None:
    for first in ("robot1", "robot1*", "*", "robot[1]", "robot10", "robot"):
        pattern = "/".join([first, *rest])
        key = zenoh.KeyExpr(KEYS.drop(pattern))
        assert ROBOT1.includes(key) == (first == "robot1"), pattern
