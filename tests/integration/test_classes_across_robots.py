"""Through a real server: a glob pattern in ``layers`` names a class, the matching robots'
layers fused by the Bayesian rule into one plane of the reply, named by the pattern.

Two robots map overlapping strips of one corridor into ``robot1/laser/obstacle`` and
``robot2/laser/obstacle`` (robot1 alone west, robot2 alone east, both in the middle); robot1
also has ``robot1/camera/person``.  The references are the per-robot layers asked by their
exact names from the same server, and the Bayesian rule in probability space (odds multiply).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import Pose2D
from sogm_service.wire.errors import ServiceError
from tests.conftest import ServerProcess, start_server, wait_processed
from tests.helpers import raw_session
from tests.integration.test_cli import one_line_error, run_cli

pytestmark = pytest.mark.integration

RES = 0.1
P1, P2, PERSON = 0.7, 0.8, 0.9  # robot1's, robot2's obstacle probability; robot1's person
# The window: x in [-4, 4), y in [-1, 1), on the map's cells (80 x 20).
WINDOW: dict[str, Any] = dict(x=0.0, y=0.0, width=8.0, height=2.0, resolution=RES, interp="nearest")
WEST, MIDDLE, EAST = slice(0, 35), slice(35, 45), slice(45, 80)  # columns of the window
LASERS = "*/laser/obstacle"


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    server = start_server(tmp_path_factory.mktemp("classes"), {"map": {"resolution": RES}})
    with server.client() as c:
        strip = np.ones((20, 45), dtype=np.float32)  # 4.5 m x 2 m
        c.publish_ism("ism/robot1/laser/obstacle", strip * P1, resolution=RES,
                      origin=Pose2D(-4.0, -1.0, 0.0))  # x in [-4, 0.5)
        c.publish_ism("ism/robot2/laser/obstacle", strip * P2, resolution=RES,
                      origin=Pose2D(-0.5, -1.0, 0.0))  # x in [-0.5, 4)
        c.publish_ism("ism/robot1/camera/person", strip * PERSON, resolution=RES,
                      origin=Pose2D(-4.0, -1.0, 0.0))
        assert wait_processed(c, 3).get("isms_fused") == 3
    yield server
    server.terminate()


def _fixed(p: float) -> int:
    return int(logodds.prob_to_fixed(p))


def test_a_pattern_is_one_layer_holding_both_robots(srv: ServerProcess) -> None:
    with srv.client() as c:
        both = c.submap(**WINDOW, layers=["robot1/laser/obstacle", "robot2/laser/obstacle"],
                        encoding="logodds_i16")
        cls = c.submap(**WINDOW, layers=[LASERS], encoding="logodds_i16")
    assert cls.layers == [LASERS] and cls.data.shape == (1, 20, 80)
    assert cls.classes == {LASERS: ["robot1/laser/obstacle", "robot2/laser/obstacle"]}
    plane = cls.data[0].astype(np.int64)
    r1, r2 = both.data.astype(np.int64)
    assert (r1[:, WEST] == _fixed(P1)).all() and (r2[:, WEST] == 0).all()  # the areas differ
    assert (r2[:, EAST] == _fixed(P2)).all() and (r1[:, EAST] == 0).all()
    assert (plane[:, WEST] == _fixed(P1)).all()  # robot1 alone: its evidence
    assert (plane[:, EAST] == _fixed(P2)).all()  # robot2 alone: its evidence
    lo, hi = logodds.clamp_limits()
    assert np.array_equal(plane, np.clip(r1 + r2, lo, hi))  # both: the log-odds add
    odds = P1 / (1 - P1) * P2 / (1 - P2)  # the Bayesian rule in probability space
    fused_p = logodds.fixed_to_prob(plane[:, MIDDLE])
    assert np.allclose(fused_p, odds / (1 + odds), atol=1e-3)


def test_patterns_with_brackets_and_exact_names_mix(srv: ServerProcess) -> None:
    with srv.client() as c:
        reply = c.submap(**WINDOW, layers=["robot[12]/laser/*", "robot1/camera/person",
                                           "robot1/*"], encoding="logodds_i16")
        whole = c.submap(**WINDOW, layers=[LASERS], encoding="logodds_i16")
    assert reply.layers == ["robot[12]/laser/*", "robot1/camera/person", "robot1/*"]
    assert reply.classes == {"robot[12]/laser/*": ["robot1/laser/obstacle",
                                                   "robot2/laser/obstacle"],
                             "robot1/*": ["robot1/camera/person", "robot1/laser/obstacle"]}
    assert np.array_equal(reply.data[0], whole.data[0])
    assert (reply.data[1][:, WEST] == _fixed(PERSON)).all()
    hi = logodds.clamp_limits()[1]
    assert (reply.data[2][:, WEST] == min(_fixed(PERSON) + _fixed(P1), hi)).all()


def test_fused_over_two_patterns_pools_the_classes(srv: ServerProcess) -> None:
    with srv.client() as c:
        classes = c.submap(**WINDOW, layers=[LASERS, "*/camera/person"],
                           encoding="logodds_i16").data.astype(np.int64)
        bayes = c.fused(**WINDOW, layers=[LASERS, "*/camera/person"], encoding="logodds_i16")
        most = c.fused(**WINDOW, method="max", layers=[LASERS, "*/camera/person"],
                       encoding="logodds_i16")
    assert bayes.layers == [LASERS, "*/camera/person"] and bayes.data.shape == (20, 80)
    assert bayes.classes == {LASERS: ["robot1/laser/obstacle", "robot2/laser/obstacle"],
                             "*/camera/person": ["robot1/camera/person"]}
    assert np.array_equal(bayes.data, classes[0] + classes[1])  # Eq. 6 P_B over the classes
    # Eq. 6 P_M over the classes that observed a cell (a class's 0 is no opinion)
    observed = np.where(classes != 0, classes, np.iinfo(np.int16).min).max(axis=0)
    assert np.array_equal(most.data, np.where((classes != 0).any(axis=0), observed, 0))
    assert (bayes.data[:, EAST] == _fixed(P2)).all()  # robot2's, no person seen there


def test_supercells_take_a_class_as_one_feature(srv: ServerProcess) -> None:
    with srv.client() as c:
        reply = c.supercells(x=0.0, y=0.0, width=6.4, height=1.6, resolution=RES,
                             layers=[LASERS, "robot1/camera/person"], encoding="prob_u8")
    assert reply.layers == [LASERS, "robot1/camera/person"]
    assert reply.classes == {LASERS: ["robot1/laser/obstacle", "robot2/laser/obstacle"]}
    assert reply.nodes and all(len(n.mean_probability) == 2 for n in reply.nodes)
    east = [n for n in reply.nodes if n.x > 1.5]
    assert east and all(abs(n.mean_probability[0] - P2) < 0.01 for n in east)


def test_a_pattern_reply_is_one_plane_of_bytes(srv: ServerProcess) -> None:
    """One class instead of the robots' layers: the reply's bytes, measured raw."""
    with srv.client() as c:
        c.compression = None
        params = dict(WINDOW, encoding="prob_f32")
        per_robot = c.get_raw(c.key("submap"), dict(
            params, layers=["robot1/laser/obstacle", "robot2/laser/obstacle"]))
        one = c.get_raw(c.key("submap"), dict(params, layers=[LASERS]))
    cells = 20 * 80 * 4
    assert len(per_robot) > 2 * cells and cells < len(one) < cells + 1024
    print(f"\nsub-map of 80 x 20 cells, prob_f32: both robots' layers {len(per_robot)} B, "
          f"the class {len(one)} B")


def test_a_pattern_matching_nothing_is_refused_and_counted(srv: ServerProcess) -> None:
    with srv.client() as c:
        before = c.stats().counters.get("query_errors_unknown_layer", 0)
        for what in (c.submap, c.fused):
            with pytest.raises(ServiceError) as err:
                what(**WINDOW, layers=[LASERS, "*/lidar/*"])
            assert (err.value.code, err.value.parameter) == ("unknown_layer", "layers")
            assert "*/lidar/*" in err.value.message
        assert c.stats().counters["query_errors_unknown_layer"] == before + 2
        assert sorted(c.info().layers) == ["robot1/camera/person", "robot1/laser/obstacle",
                                           "robot2/laser/obstacle"]


def test_a_raw_zenoh_get_names_a_class_in_the_selector_and_in_a_body(
        srv: ServerProcess) -> None:
    session = raw_session(srv.endpoint)
    try:
        (sel,) = list(session.get(f"sogm/default/submap?layers={LASERS};width=2;height=2",
                                  timeout=5.0))
        (body,) = list(session.get("sogm/default/submap", timeout=5.0, payload=msgpack.packb(
            {"layers": [LASERS], "width": 2, "height": 2})))
    finally:
        session.close()
    assert sel.ok is not None and body.ok is not None
    a, b = (msgpack.unpackb(ok.payload.to_bytes()) for ok in (sel.ok, body.ok))
    assert a["layers"] == b["layers"] == [LASERS] and a["data"] == b["data"]


def test_the_cli_asks_a_class_and_names_its_members(srv: ServerProcess,
                                                    tmp_path: Path) -> None:
    png = tmp_path / "lasers.png"
    proc = run_cli("query", "submap", "--connect", srv.endpoint, "--width", "8", "--height",
                   "2", "--resolution", str(RES), "--layers", f"{LASERS},robot1/camera/person",
                   "--png", str(png), "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["layers"] == [LASERS, "robot1/camera/person"]
    assert out["classes"] == {LASERS: ["robot1/laser/obstacle", "robot2/laser/obstacle"]}
    assert sorted(Path(p).name for p in out["written"]) == [
        "lasers_all_laser_obstacle.png", "lasers_robot1_camera_person.png"]
    assert all(Path(p).stat().st_size > 0 for p in out["written"])
    text = run_cli("query", "fused", "--connect", srv.endpoint, "--layers", LASERS)
    assert f"class {LASERS}: robot1/laser/obstacle + robot2/laser/obstacle" in text.stdout
    refused = one_line_error(run_cli("query", "submap", "--connect", srv.endpoint,
                                     "--layers", "*/lidar/*"))
    assert "unknown_layer" in refused and "*/lidar/*" in refused
