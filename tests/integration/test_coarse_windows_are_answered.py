"""A real server answers a coarse window over a large area (it is gathered) and still refuses
the same window at map resolution."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from sogm_service.core.geometry import Pose2D
from sogm_service.core.resample import INTERPOLATIONS
from sogm_service.wire.errors import ServiceError
from tests.conftest import ServerProcess, start_server, wait_processed

pytestmark = pytest.mark.integration


FAR = [(-150.0, -150.0), (140.0, 120.0)]  # ISM corners, 290 m and 270 m apart


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    server = start_server(tmp_path_factory.mktemp("coarse"))
    with server.client() as c:
        for k, (x, y) in enumerate(FAR):
            grid = np.full((200, 200), 230 if k == 0 else 40, dtype=np.uint8)  # 10 m square
            c.publish_ism(f"ism/r1/cam/{k}", grid, resolution=0.05, origin=Pose2D(x, y, 0.0),
                          layer="obstacle")
        assert wait_processed(c, 2).get("isms_fused") == 2
    yield server
    server.terminate()


@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_a_400m_window_at_4m_is_answered(srv: ServerProcess, interp: str) -> None:
    with srv.client() as c:
        reply = c.submap(width=400, height=400, resolution=4, interp=interp,
                         encoding="logodds_i16")
        grid = np.asarray(reply.data)
        assert grid.shape[-2:] == (100, 100)
        grid = grid.reshape(100, 100)
        # the value of one map cell, read by a window at map resolution (the full path)
        inside = [int(np.asarray(c.submap(x=x + 4, y=y + 4, width=0.05, height=0.05,
                                          encoding="logodds_i16").data).ravel()[0])
                  for x, y in FAR]
        assert inside[0] > 1000 and inside[1] < -1000
        # output cell (col, row) covers [-200 + 4 col, -196 + 4 col]: (13, 13) and (14, 14)
        # lie inside the first square, (85, 80) and (85, 81) inside the second
        for col, row in [(13, 13), (14, 14), (13, 14)]:
            assert grid[row, col] == inside[0]
        for col, row in [(85, 80), (85, 81), (86, 81)]:
            assert grid[row, col] == inside[1]
        # nothing is known away from the two squares (cells on their edges may be)
        rows, cols = np.nonzero(grid)
        for row, col in zip(rows.tolist(), cols.tolist(), strict=True):
            assert (12 <= col <= 15 and 12 <= row <= 15) or \
                (84 <= col <= 87 and 79 <= row <= 82), (col, row)


def test_the_same_window_at_map_resolution_is_still_refused(srv: ServerProcess) -> None:
    with srv.client() as c:
        with pytest.raises(ServiceError) as err:
            c.submap(width=400, height=400, encoding="prob_u8")
        assert err.value.code == "window_too_large"
        # and one that is not coarse enough to gather: the cells it reads are named
        with pytest.raises(ServiceError) as err:
            c.submap(width=300, height=300, resolution=0.1, encoding="prob_u8")
        assert err.value.code == "window_too_large" and "reads 36024004" in err.value.message
        assert "query_errors_internal" not in c.stats().counters
