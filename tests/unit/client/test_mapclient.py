"""The map client's own checks: what it refuses before anything is sent."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.client import InvalidIsmError


def test_client_refuses_bad_grids_before_sending() -> None:
    from sogm_service.client.mapclient import build_ism

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
