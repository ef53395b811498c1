"""The map client's own checks: what it refuses before anything is sent."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from sogm_service.client import InvalidIsmError
from sogm_service.client.isms import ism_footprint


def test_client_refuses_bad_grids_before_sending() -> None:
    from sogm_service.client.isms import build_ism

    with pytest.raises(InvalidIsmError, match="2-D"):
        build_ism(np.zeros((10, 3, 2), np.uint8), resolution=0.1)
    with pytest.raises(InvalidIsmError, match="dtype"):
        build_ism(np.zeros((3, 3), np.int64), resolution=0.1)
    with pytest.raises(InvalidIsmError, match="do not fit"):
        build_ism(np.full((3, 3), 0.5, np.float32), resolution=0.1, encoding="prob_u8")
    with pytest.raises(InvalidIsmError, match="resolution"):
        build_ism(np.zeros((3, 3), np.uint8), resolution=-1.0)
    assert build_ism(np.zeros((3, 3), np.int64), resolution=0.1,
                     encoding="occupancy_i8").encoding == "occupancy_i8"


def test_ism_footprint_from_a_header_built_by_msgpack_alone() -> None:
    # The spec's fields, packed by msgpack itself (not the project's encoder).
    header = {"resolution": 0.1, "width": 20, "height": 10, "encoding": "prob_u8",
              "origin": {"x": 1.0, "y": 2.0, "yaw": math.pi / 2}, "robot": "r9",
              "data": bytes(200)}
    fp = ism_footprint("ism/r9/cam/chair", msgpack.packb(header))
    assert fp is not None and fp.robot == "r9" and fp.layer is None
    expected = [(1.0, 2.0), (1.0, 4.0), (0.0, 4.0), (0.0, 2.0)]  # rotated 90 degrees
    assert np.allclose(fp.corners, expected)
    for bad in (b"\xc1garbage", msgpack.packb([1, 2]), msgpack.packb({**header, "width": -1}),
                msgpack.packb({**header, "resolution": float("nan")}),
                msgpack.packb({**header, "origin": {"x": "a"}}),
                msgpack.packb({k: v for k, v in header.items() if k != "height"})):
        assert ism_footprint("ism/x", bad) is None
