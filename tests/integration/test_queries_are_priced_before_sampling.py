"""Through a real server: queries are priced before sampling (cells read at map
resolution, reply bytes, heavy queries at once); no number can make one fail as internal."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sogm_service.client.mapclient import MapClient
from sogm_service.core.geometry import Pose2D
from sogm_service.wire.errors import QUERY_CODES, ServiceError
from tests.conftest import ServerProcess, start_server, wait_processed
from tests.integration.test_hostile_isms_are_refused import RSS_BOUND_MB, baseline_rss_mb, rss_mb

pytestmark = pytest.mark.integration

SPECIFIC = {"bad_parameter", "window_too_large", "out_of_world", "reply_too_large",
            "unknown_layer"}


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    server = start_server(tmp_path_factory.mktemp("bounds_query"),
                          {"limits": {"max_reply_bytes": 100_000, "max_heavy_queries": 1}})
    with server.client() as c:
        grid = np.random.default_rng(3).integers(0, 256, (200, 200), dtype=np.uint8)
        c.publish_ism("ism/r1/obstacle", grid, resolution=0.05, origin=Pose2D(-5, -5, 0.0),
                      layer="obstacle")
        assert wait_processed(c, 1).get("isms_fused") == 1
    yield server
    server.terminate()


def _code(client: MapClient, what: str, params: dict[str, object]) -> str:
    try:
        client.get_raw(client.key(what), params)
    except ServiceError as exc:
        return exc.code
    return "ok"


@pytest.mark.parametrize(("params", "code"), [
    ({"width": "1e308"}, "window_too_large"),
    ({"height": "1e308"}, "window_too_large"),
    ({"x": "1e308"}, "out_of_world"),
    ({"y": "-1e308"}, "out_of_world"),
    ({"x": "1e7"}, "out_of_world"),  # beyond the default world of 1,000 km
    ({"resolution": "1e-300"}, "window_too_large"),
    ({"resolution": "1e308"}, "window_too_large"),
    ({"width": "inf"}, "bad_parameter"),
    ({"x": "nan"}, "bad_parameter"),
    ({"yaw": "1e308"}, "ok"),  # a finite heading is a heading
    # the 100x100 reply of a 400 m window at 4 m cells read 64 M map cells; now it
    # gathers 40 k (tests/unit/core/map/test_gather.py); 300 m at 0.1 m still reads 36 M
    ({"width": "400", "height": "400", "resolution": "4"}, "ok"),
    ({"width": "300", "height": "300", "resolution": "0.1"}, "window_too_large"),
    # 200 x 200 cells: 40 kB as prob_u8, 160 kB as prob_f32 (max_reply_bytes = 100 kB)
    ({"width": "10", "height": "10", "encoding": "prob_u8"}, "ok"),
    ({"width": "10", "height": "10", "encoding": "prob_f32"}, "reply_too_large"),
])
@pytest.mark.parametrize("what", ["submap", "fused"])
def test_absurd_numbers_get_their_code(srv: ServerProcess, what: str,
                                       params: dict[str, object], code: str) -> None:
    with srv.client() as c:
        assert _code(c, what, params) == code
        assert code == "ok" or code in QUERY_CODES


def test_the_read_cells_are_named_in_the_refusal(srv: ServerProcess) -> None:
    with srv.client() as c, pytest.raises(ServiceError) as err:
        c.submap(width=300, height=300, resolution=0.1)
    assert err.value.code == "window_too_large"
    assert "reads 36024004" in err.value.message and "map cells" in err.value.message


def test_supercells_window_is_bounded(srv: ServerProcess) -> None:
    with srv.client() as c:
        # 60 m at 5 cm: 1.44 M cells > max_supercell_cells (1 M) though < max_query_cells
        assert _code(c, "supercells", {"width": 60, "height": 60,
                                       "encoding": "prob_u8"}) == "window_too_large"


floats = st.one_of(st.floats(), st.sampled_from([0.0, 1e-300, 1e308, -1e308, 5e5, 2e6]),
                   st.floats(-50, 50))


@settings(max_examples=80, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(x=floats, y=floats, yaw=floats, width=floats, height=floats,
       resolution=st.one_of(st.none(), floats))
def test_no_window_parameters_cause_an_internal_error(
        srv: ServerProcess, x: float, y: float, yaw: float, width: float, height: float,
        resolution: float | None) -> None:
    with srv.client() as c:
        code = _code(c, "submap", {"x": x, "y": y, "yaw": yaw, "width": width,
                                   "height": height, "resolution": resolution,
                                   "encoding": "prob_u8"})
        assert code == "ok" or code in SPECIFIC, code


def test_a_burst_of_large_windows_keeps_rss_and_the_map(srv: ServerProcess) -> None:
    with srv.client() as c:
        before_map = c.submap(width=10, height=10, encoding="logodds_i16").data.tobytes()
        before = baseline_rss_mb(c, srv.proc.pid)
        for k in range(30):
            for params in ({"width": 300, "height": 300, "resolution": 0.1},
                           {"width": 210, "height": 210, "resolution": 0.1 + k / 1000},
                           {"width": "1e308"}):
                assert _code(c, "submap", params) == "window_too_large"
            # answered since it is gathered: 40 k map cells, not 64 M
            assert _code(c, "submap", {"width": 400, "height": 400, "resolution": 4}) == "ok"
        assert rss_mb(srv.proc.pid) - before < RSS_BOUND_MB
        assert c.submap(width=10, height=10, encoding="logodds_i16").data.tobytes() \
            == before_map
        assert "query_errors_internal" not in c.stats().counters
