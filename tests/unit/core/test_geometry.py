"""A grid's centre, computed in plain floats on every ISM's header, is where its cell lattice
and its corners put it."""

from __future__ import annotations

import numpy as np
import pytest

from sogm_service.core.geometry import GridGeometry, Pose2D


@pytest.mark.parametrize(("w", "h", "res", "pose"), [
    (252, 252, 0.05, Pose2D(1.7, -3.2, 0.0)),
    (64, 17, 0.25, Pose2D(-40.0, 12.5, 0.5)),
    (1, 3, 0.1, Pose2D(0.0, 0.0, -2.9)),
])
def test_the_centre_is_the_middle_of_the_cells_and_of_the_corners(
        w: int, h: int, res: float, pose: Pose2D) -> None:
    g = GridGeometry(res, w, h, pose)
    middle_cell = g.cell_to_world() @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    np.testing.assert_allclose(g.centre(), middle_cell[:2], atol=1e-9)
    np.testing.assert_allclose(g.centre(), g.corners().mean(axis=0), atol=1e-9)
    assert all(isinstance(v, float) for v in g.centre())
