"""The pipeline remembers each ISM key's robot and layer (a cluster member checks every ISM
of the fleet): what it remembers is bounded, and it never lets a message name another robot."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.service.config import ServiceConfig
from sogm_service.service.server import pipeline
from sogm_service.service.server.pipeline import IngestPipeline, IsmItem
from sogm_service.service.server.server import MapServer
from sogm_service.wire.errors import IsmRejectedError
from sogm_service.wire.messages import IsmMessage, PoseModel


def _pipeline() -> IngestPipeline:
    return MapServer(ServiceConfig()).pipeline  # not started: the pipeline alone


def _ism(robot: str | None = None, layer: str | None = None) -> IsmMessage:
    return IsmMessage(resolution=0.05, origin=PoseModel(x=1.0, y=1.0), width=4, height=4,
                      encoding="prob_u8", data=np.full(16, 200, np.uint8).tobytes(),
                      robot=robot, layer=layer, stamp=5.0)


def test_a_remembered_key_still_checks_the_robot_its_message_names() -> None:
    p = _pipeline()
    key = "ism/r1/laser/obstacle"
    assert p.identify(IsmItem(0, key), _ism("r1")) == "r1/laser/obstacle"
    assert p.identify(IsmItem(0, key), _ism(None, layer="walls")) == "walls"
    assert p.identify(IsmItem(0, key), _ism("r1")) == "r1/laser/obstacle"  # remembered
    with pytest.raises(IsmRejectedError) as refused:  # the same key, another robot named
        p.identify(IsmItem(0, key), _ism("r2"))
    assert refused.value.code == "robot_mismatch"


def test_what_the_pipeline_remembers_is_bounded() -> None:
    p = _pipeline()
    for k in range(pipeline.NAMES_KEPT + 10):
        assert p.identify(IsmItem(0, f"ism/r{k}/obstacle"), _ism()) == f"r{k}/obstacle"
    assert len(p._names) <= pipeline.NAMES_KEPT
