"""nav2's keepout and speed filter masks, derived live from the semantic layers by a real
``serve --ros2`` with a ``[nav2]`` section, as a ROS 2 subscriber (nav2's costmap filters) gets
them: ``/sogm/<map>/keepout_mask`` and ``speed_mask`` (whole grids and ``_updates``) with their
transient-local ``nav2_msgs/msg/CostmapFilterInfo``.

A person seen in a layer that forgets is kept out (100), fades to 0 once its evidence is below
the threshold and to -1 once it is gone, as the map's clock (the latest ISM stamp) moves on; a
pallet limits the speed to 40 % and does not fade.  nav2's filters read whole grids only, so
by default (``whole_masks``) every change is a whole grid; without it the changes go on
``_updates`` as for the map.  The ROS side is built from the message
definitions with rosbags (CostmapFilterInfo and OccupancyGridUpdate registered from their text,
hashes computed by rosbags) and rmw_zenoh's wire as documented; nothing on it uses the project's
encoders.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

import zenoh.ext
from rosbags.typesys import get_types_from_msg

from sogm_service.client import MapClient
from sogm_service.client.session import loopback_settings, open_session
from sogm_service.core.geometry import Pose2D
from tests.conftest import start_server, wait_processed, wait_until
from tests.integration.test_cli import run_cli
from tests.integration.test_ros2_bridge import GRID_H, GRID_T, TS, tokens
from tests.integration.test_ros2_map_updates import UPDATE_H, UPDATE_T, Holder
from tests.unit.adapters.ros2.test_filters import map_server_scale
from tests.unit.adapters.test_nav2 import map_server_trinary, read_pgm

pytestmark = pytest.mark.integration

MAP = "navmap"
TIMEOUT = 15.0
RES = 0.05
INFO = "nav2_msgs/msg/CostmapFilterInfo"
INFO_T = "nav2_msgs::msg::dds_::CostmapFilterInfo_"
if INFO not in TS.types:
    TS.register(get_types_from_msg("std_msgs/Header header\nuint8 type\n"
                                   "string filter_mask_topic\nfloat32 base\n"
                                   "float32 multiplier\n", INFO))
INFO_H = TS.hash_rihs01(INFO)


@dataclass
class Infos:
    """The CostmapFilterInfo messages one subscriber got, decoded with rosbags."""

    got: list[Any] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: Any) -> None:
        m = TS.deserialize_cdr(sample.payload.to_bytes(), INFO)
        with self.lock:
            self.got.append(m)

    def all(self) -> list[Any]:
        with self.lock:
            return list(self.got)


def cells_at(holder: Holder, x: float, y: float, w: float, h: float) -> np.ndarray:
    """The mask's cells of the world box [x, x + w) x [y, y + h) (the grid's origin: 0, 0)."""
    grid = holder.cells()
    assert grid is not None and holder.grid is not None
    o = holder.grid.info.origin.position
    c0, r0 = round((x - o.x) / RES), round((y - o.y) / RES)
    return grid[r0:r0 + round(h / RES), c0:c0 + round(w / RES)]


def check_viewer_keepout(endpoint: str) -> None:
    """``view --keepout "*/person"``'s hub draws the keepout display tile red over the person
    and leaves the pallet as the map shows it."""
    cv2 = pytest.importorskip("cv2")
    from sogm_service.adapters.ros2.filters import FilterSpec
    from sogm_service.apps.viewer.hub import HubSettings, MapHub
    from sogm_service.apps.viewer.pictures import KEEPOUT_BGR
    from sogm_service.apps.viewer.tiles import TileSpec

    hub = MapHub(HubSettings(endpoint=endpoint, map_name=MAP,
                             filters=FilterSpec(keepout=("*/person",)))).start()
    try:
        assert wait_until(lambda: hub.lattice() is not None, TIMEOUT)
        span = 64 * RES  # lattice tile (0, 0) at level 0: 64 pixels of 5 cm
        pictures = {}
        for mode in ("keepout", "class"):
            spec = TileSpec(mode, 0, 0, 0, 0.0, 0.0, span, 64)
            assert wait_until(lambda s=spec: hub.tile(s, 0.0) is not None, TIMEOUT)  # type: ignore[misc]
            tile = hub.tile(spec, 0.0)
            assert tile is not None
            img = cv2.imdecode(np.frombuffer(tile.png, np.uint8), cv2.IMREAD_COLOR)
            pictures[mode] = img[::-1]  # map order: row 0 at the smallest y
        keep = pictures["keepout"].astype(float)
        person = keep[20:40, 20:30].reshape(-1, 3)  # x 1.0-1.5, y 1.0-2.0
        pallet = keep[20:40, 40:60].reshape(-1, 3)
        assert np.all(np.abs(person - KEEPOUT_BGR).sum(axis=1) < 120)
        assert np.all(np.abs(pallet - KEEPOUT_BGR).sum(axis=1) > 200)
    finally:
        hub.close()


@pytest.mark.parametrize("whole_masks", [True, False], ids=["whole", "updates"])
def test_keepout_follows_a_person_and_fades_and_speed_limits_a_pallet(
        tmp_path: Any, whole_masks: bool) -> None:
    srv = start_server(tmp_path, {
        "map": {"name": MAP, "resolution": RES, "tile_size": 64, "forget": {"*/person": 1.0}},
        "ros2": {"enabled": True, "publish_period_s": 0.2, "region": "known",
                 "full_period_s": 0},
        "nav2": {"keepout": ["*/person"], "keepout_threshold": 0.6,
                 "speed": {"*/pallet": 40}, "whole_masks": whole_masks}})
    ros = open_session(loopback_settings(connect=srv.endpoint))
    keep, speed = Holder(), Holder()
    keep_info, speed_info = Infos(), Infos()
    base = f"0/sogm/{MAP}"
    subs = [ros.declare_subscriber(f"{base}/keepout_mask/{GRID_T}/{GRID_H}", keep.on_grid),
            ros.declare_subscriber(f"{base}/keepout_mask_updates/{UPDATE_T}/{UPDATE_H}",
                                   keep.on_update),
            ros.declare_subscriber(f"{base}/speed_mask/{GRID_T}/{GRID_H}", speed.on_grid),
            ros.declare_subscriber(f"{base}/speed_mask_updates/{UPDATE_T}/{UPDATE_H}",
                                   speed.on_update),
            ros.declare_subscriber(f"{base}/keepout_filter_info/{INFO_T}/{INFO_H}",
                                   keep_info.on_sample),
            ros.declare_subscriber(f"{base}/speed_filter_info/{INFO_T}/{INFO_H}",
                                   speed_info.on_sample)]
    late = None
    try:
        with MapClient.connect(srv.endpoint, map_name=MAP) as client:
            t0 = time.time()
            person = np.full((20, 20), 95, np.int8)  # occupied: somebody there
            person[:, 10:] = 5  # the detector saw nobody there
            client.publish_ism("ism/robot1/person", person, resolution=RES,
                               origin=Pose2D(1.0, 1.0, 0.0), stamp=t0)
            client.publish_ism("ism/robot2/pallet", np.full((20, 20), 90, np.int8),
                               resolution=RES, origin=Pose2D(2.0, 1.0, 0.0), stamp=t0)
            client.publish_ism("ism/robot2/walls", np.full((4, 4), 90, np.int8),
                               resolution=RES, origin=Pose2D(0.2, 0.2, 0.0), stamp=t0)
            assert wait_processed(client, 3).get("isms_fused") == 3

            def person_kept_out() -> bool:
                c = keep.cells()
                return c is not None and keep.grid is not None and \
                    bool(np.all(cells_at(keep, 1.0, 1.0, 0.5, 1.0) == 100))
            assert wait_until(person_kept_out, TIMEOUT), "no keepout where the person is"
            assert np.all(cells_at(keep, 1.5, 1.0, 0.5, 1.0) == 0)  # seen: nobody there
            assert np.all(cells_at(keep, 2.0, 1.0, 1.0, 1.0) == -1)  # no person layer saw it
            # the mask is the rule applied to the class as the server reads it natively
            g = keep.grid
            native = client.submap(x=g.info.origin.position.x + g.info.width * RES / 2,
                                   y=g.info.origin.position.y + g.info.height * RES / 2,
                                   width=g.info.width * RES, height=g.info.height * RES,
                                   resolution=RES, interp="nearest", encoding="logodds_i16",
                                   layers=["*/person"]).data[0].astype(np.float64)
            p = 1 / (1 + np.exp(-native / 1000))
            want = np.where(native == 0, -1, np.where(p >= 0.6, 100, 0)).astype(np.int8)
            got = keep.cells()
            assert got is not None and np.array_equal(got, want)

            # the pallet may have been fused a period after the person: wait for its limit
            assert wait_until(lambda: speed.cells() is not None and speed.grid is not None and
                              bool(np.all(cells_at(speed, 2.0, 1.0, 1.0, 1.0) == 40)), TIMEOUT)
            sp = speed.cells()
            assert sp is not None and int(np.count_nonzero(sp == 40)) == 400
            assert set(np.unique(sp).tolist()) == {0, 40}  # no limit elsewhere, never -1
            assert (speed.grid.info.width, speed.grid.info.height) == \
                (g.info.width, g.info.height)  # the map's extent
            assert speed.grid.info.origin.position.x == g.info.origin.position.x

            # export nav2 --keepout/--speed: the same masks as files map_server reads
            out = tmp_path / "masks"
            x0, y0 = g.info.origin.position.x, g.info.origin.position.y
            run = run_cli("export", "nav2", "--out", str(out), "--connect", srv.endpoint,
                          "--map", MAP, "--keepout", "*/person", "--speed", "*/pallet=40",
                          "--box", str(x0), str(y0), str(x0 + g.info.width * RES),
                          str(y0 + g.info.height * RES))
            assert run.returncode == 0, run.stderr
            for mask, holder in (("keepout", keep), ("speed", speed)):
                doc = yaml.safe_load((out / f"{mask}_mask.yaml").read_text())
                px = np.flipud(read_pgm(out / doc["image"]))
                if mask == "keepout":
                    assert doc["mode"] == "trinary"
                    cells = map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"],
                                               doc["negate"])
                else:
                    assert doc["mode"] == "scale"
                    cells = map_server_scale(px, doc["occupied_thresh"], doc["free_thresh"])
                assert doc["origin"][:2] == pytest.approx([x0, y0])
                assert np.array_equal(cells, holder.cells()), mask

            if whole_masks:  # the viewer's overlay of the same mask: red over the person
                check_viewer_keepout(srv.endpoint)

            # filter info: latched, what nav2's filters read, and exactly once per topic
            assert wait_until(lambda: keep_info.all() and speed_info.all(), TIMEOUT)
            for infos, ftype, topic in ((keep_info, 0, f"/sogm/{MAP}/keepout_mask"),
                                        (speed_info, 1, f"/sogm/{MAP}/speed_mask")):
                m = infos.all()[0]
                assert (m.type, m.base, m.multiplier, m.filter_mask_topic,
                        m.header.frame_id) == (ftype, 0.0, 1.0, topic, "map")
            lv = tokens(ros)
            assert any(f"%sogm%{MAP}%keepout_filter_info/{INFO_T}/{INFO_H}/" in t
                       for t in lv), "no publisher token for the filter info"
            # a late subscriber (nav2 starting later) gets the latched filter info
            late_info = Infos()
            late = zenoh.ext.declare_advanced_subscriber(
                ros, f"{base}/speed_filter_info/{INFO_T}/{INFO_H}", late_info.on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            assert wait_until(lambda: late_info.all(), TIMEOUT)
            assert late_info.all()[0].type == 1

            # the map's clock moves on: 4 half-lives, the person's 95 % is 55 %: no keepout
            client.publish_ism("ism/robot2/walls", np.full((4, 4), 90, np.int8),
                               resolution=RES, origin=Pose2D(0.2, 0.2, 0.0), stamp=t0 + 4)
            assert wait_processed(client, 4).get("isms_fused") == 4
            assert wait_until(lambda: np.all(cells_at(keep, 1.0, 1.0, 0.5, 1.0) == 0),
                              TIMEOUT), "the keepout did not fade"
            # 30 half-lives: nothing is left of the person, unknown again
            client.publish_ism("ism/robot2/walls", np.full((4, 4), 90, np.int8),
                               resolution=RES, origin=Pose2D(0.2, 0.2, 0.0), stamp=t0 + 30)
            assert wait_processed(client, 5).get("isms_fused") == 5
            assert wait_until(lambda: np.all(cells_at(keep, 1.0, 1.0, 1.0, 1.0) == -1),
                              TIMEOUT), "the faded keepout never became unknown"
            time.sleep(0.6)  # a few more periods: the pallet does not fade
            assert np.all(cells_at(speed, 2.0, 1.0, 1.0, 1.0) == 40)
            ros2 = client.stats().extra["ros2"]
            print(f"\nkeepout_mask: {len(keep.fulls)} whole grids of "
                  f"{sum(b for _, b in keep.fulls)} bytes, {len(keep.updates)} updates of "
                  f"{sum(b for _, b, _ in keep.updates)} bytes; speed_mask: "
                  f"{len(speed.fulls)} whole grids of {sum(b for _, b in speed.fulls)} bytes, "
                  f"{len(speed.updates)} updates; grid {g.info.width}x{g.info.height}; "
                  f"server counters {ros2.get('counters', ros2)}")
            if whole_masks:  # what nav2's filters read: each change a whole grid, no update
                assert len(keep.fulls) >= 3 and not keep.updates  # kept out, faded, gone
            else:  # the fade went as updates, as for the map
                assert len(keep.fulls) == 1 and len(keep.updates) >= 2 and keep.misplaced == 0
            assert len(keep_info.all()) == 1 and len(speed_info.all()) == 1
    finally:
        if late is not None:
            late.undeclare()
        for s in subs:
            s.undeclare()
        ros.close()
        assert srv.terminate() == 0
