"""Classes of layers (core/classes.py): glob patterns resolved over layer names, and each
class fused by the Bayesian rule in probability space (odds multiply), clamped as the map."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.classes import (
    LayerClass,
    NoMatchingLayerError,
    fuse_classes,
    is_pattern,
    member_layers,
    resolve,
)

NAMES = ["robot2/laser/obstacle", "robot1/laser/obstacle", "robot1/camera/person",
         "robot3/laser/obstacle"]


def test_is_pattern() -> None:
    assert is_pattern("*/laser/obstacle") and is_pattern("robot?") and is_pattern("r[12]")
    assert not is_pattern("robot1/laser/obstacle") and not is_pattern("a-b_c.d")


def test_resolve_exact_names_and_patterns() -> None:
    classes = resolve(["robot1/camera/person", "*/laser/obstacle", "robot3/*", "robot[12]/*"],
                      NAMES)
    assert classes == [
        LayerClass("robot1/camera/person", ("robot1/camera/person",)),
        LayerClass("*/laser/obstacle", ("robot1/laser/obstacle", "robot2/laser/obstacle",
                                        "robot3/laser/obstacle")),
        LayerClass("robot3/*", ("robot3/laser/obstacle",)),  # '*' crosses '/'
        LayerClass("robot[12]/*", ("robot1/camera/person", "robot1/laser/obstacle",
                                   "robot2/laser/obstacle")),
    ]
    assert member_layers(classes)[:2] == ["robot1/camera/person", "robot1/laser/obstacle"]
    assert len(member_layers(classes)) == 4


def test_resolve_is_case_sensitive() -> None:
    assert resolve(["ROBOT1/*"], NAMES, allow_empty=True) == [LayerClass("ROBOT1/*", ())]


def test_unmatched_entries_are_refused_or_empty() -> None:
    with pytest.raises(NoMatchingLayerError) as err:
        resolve(["*/lidar", "robot1/laser/obstacle", "nope"], NAMES)
    assert err.value.unmatched == ("*/lidar", "nope")
    assert resolve(["*/lidar"], NAMES, allow_empty=True) == [LayerClass("*/lidar", ())]


def test_fuse_classes_is_the_bayesian_rule_clamped() -> None:
    lo, hi = logodds.clamp_limits()
    p1 = np.array([[0.9, 0.5, 0.2, 0.99]])
    p2 = np.array([[0.8, 0.7, 0.5, 0.99]])
    stack = np.stack([logodds.prob_to_fixed(p1), logodds.prob_to_fixed(p2),
                      logodds.prob_to_fixed(np.full((1, 4), 0.3))])
    names = ["a/x", "b/x", "a/y"]
    out = fuse_classes(stack, names, resolve(["*/x", "a/y", "none/*"], names, allow_empty=True))
    assert out.dtype == np.int16 and out.shape == (3, 1, 4)
    # independent evidence: the odds multiply (reference in probability space)
    odds = p1 / (1 - p1) * p2 / (1 - p2)
    expected = np.clip(np.log(odds) * logodds.SCALE, lo, hi)
    assert np.all(np.abs(out[0].astype(float) - expected) <= 1.0)
    assert out[0, 0, 3] == hi  # 0.99 twice is beyond the clamp
    assert np.array_equal(out[1], stack[2])  # one member: unchanged
    assert not out[2].any()  # no member: unknown


def test_fuse_classes_unknown_cells_add_nothing() -> None:
    a = np.array([[[500, 0], [0, 0]]], dtype=np.int16)
    b = np.array([[[0, -700], [0, 0]]], dtype=np.int16)
    out = fuse_classes(np.concatenate([a, b]), ["r1/l", "r2/l"], [LayerClass("*/l", ("r1/l",
                                                                                    "r2/l"))])
    assert out.tolist() == [[[500, -700], [0, 0]]]


def test_fuse_classes_uses_the_given_clamp() -> None:
    stack = np.full((2, 1, 1), 4000, dtype=np.int16)
    limits = logodds.clamp_limits(0.05)
    out = fuse_classes(stack, ["a", "b"], [LayerClass("*", ("a", "b"))], limits=limits)
    assert out[0, 0, 0] == limits[1] < 8000
