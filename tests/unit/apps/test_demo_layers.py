"""The demo's layer naming: shared layers, or per-robot layers read by class patterns."""

from __future__ import annotations

from pathlib import Path

from sogm_service.apps.demo_layers import DemoLayers, class_of, label
from sogm_service.apps.demo_person import PERSON_HALF_LIFE_S, forgetting_config
from sogm_service.core.map.forget import ForgetRules

PER_ROBOT = ["robot1/laser/obstacle", "robot1/camera/floor", "robot1/people/person",
             "robot2/laser/obstacle", "robot2/camera/floor"]


def test_shared_layers_are_read_by_their_names() -> None:
    naming = DemoLayers()
    assert naming.mode == "shared" and naming.entry("person") == "person"
    assert naming.entries(["obstacle", "floor", "person"], skip=["person"]) == ["obstacle",
                                                                                "floor"]
    assert naming.summary(["obstacle"], ["obstacle", "floor"]) == {
        "obstacle": {"entry": "obstacle", "members": ["obstacle"]}}


def test_per_robot_layers_are_read_by_one_pattern_per_class_with_every_robot_a_member() -> None:
    naming = DemoLayers(per_robot=True)
    assert naming.mode == "per_robot"
    entries = naming.entries(PER_ROBOT, skip=["person"])
    assert entries == ["*/*/obstacle", "*/*/floor"]
    summary = naming.summary([*entries, naming.entry("person")], PER_ROBOT)
    assert summary["obstacle"] == {"entry": "*/*/obstacle",
                                   "members": ["robot1/laser/obstacle", "robot2/laser/obstacle"]}
    assert summary["person"]["members"] == ["robot1/people/person"]
    # the pictures and the IoU name a pattern's plane by its class, a layer by its name
    assert [label(e) for e in entries] == ["obstacle", "floor"]
    assert label("robot1/laser/obstacle") == "robot1/laser/obstacle"
    assert class_of("robot1/laser/obstacle") == "obstacle"


def test_the_person_pattern_makes_every_robots_person_layer_forget(tmp_path: Path) -> None:
    from sogm_service.apps.demo import _config
    from sogm_service.sim import warehouse_world

    world = warehouse_world(0)
    config = forgetting_config(_config(0.05, {}, tmp_path), world,
                               DemoLayers(per_robot=True).entry("person"))
    rules = ForgetRules(config.map.forget)
    assert rules.half_life("robot1/people/person") == PERSON_HALF_LIFE_S
    assert rules.half_life("robot7/people/person") == PERSON_HALF_LIFE_S
    assert rules.half_life("robot1/laser/obstacle") is None
    assert config.nav2.keepout == ["*/*/person"]
