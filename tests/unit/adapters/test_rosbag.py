"""nav2 map files and ROS bags: written by the adapters or by rosbags, read back independently."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")  # the [ros2] extra
yaml = pytest.importorskip("yaml")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from sogm_service.adapters.nav2 import Nav2MapError, export_nav2, read_nav2  # noqa: E402
from sogm_service.adapters.rosbag import BagGrid, BagReader, BagScan  # noqa: E402
from sogm_service.core.geometry import GridGeometry, Pose2D  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)


def _read_pgm(path: Path) -> np.ndarray:
    """A plain P5 parser (header tokens, comments, maxval 255), independent of OpenCV."""
    data = path.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    assert tokens[0] == b"P5" and tokens[3] == b"255"
    w, h = int(tokens[1]), int(tokens[2])
    pixels = np.frombuffer(data[pos + 1:pos + 1 + w * h], dtype=np.uint8)
    assert pixels.size == w * h
    return pixels.reshape(h, w)


def _map_server_trinary(px: np.ndarray, occupied: float, free: float,
                        negate: int) -> np.ndarray:
    """nav2 map_server's rule for a grey image: occ = 1 - v/255 (negate 0), thresholds."""
    shade = px / 255.0
    occ = shade if negate else 1.0 - shade
    out = np.full(px.shape, -1, np.int8)
    out[occ > occupied] = 100
    out[occ < free] = 0
    return out


def test_export_nav2_is_read_as_map_server_reads_it(tmp_path: Path) -> None:
    # 4 columns x 3 rows of probabilities, row 0 at the smallest y
    probs = np.array([[0.9, 0.1, 0.5, 0.7],
                      [0.2, 0.5, 0.99, 0.0],
                      [0.5, 0.5, 0.3, 0.66]])
    geom = GridGeometry(0.05, 4, 3, Pose2D(-1.5, 2.25, 0.1))
    yml, pgm = export_nav2(tmp_path / "out", probs, geom, kind="probability")
    doc = yaml.safe_load(yml.read_text())
    assert doc["image"] == "map.pgm" and (yml.parent / doc["image"]) == pgm
    assert doc["mode"] == "trinary" and doc["negate"] == 0
    assert doc["resolution"] == 0.05 and doc["origin"] == [-1.5, 2.25, 0.1]
    assert doc["occupied_thresh"] == 0.65 and doc["free_thresh"] == 0.25
    px = _read_pgm(pgm)
    assert px.shape == (3, 4)
    # map_server: image row r -> grid row height - 1 - r, so the image's top row is max y
    grid = _map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"], doc["negate"])
    grid = grid[::-1]
    expect = np.where(probs >= 0.65, 100, np.where(probs <= 0.25, 0, -1))
    expect[probs == 0.5] = -1
    assert np.array_equal(grid, expect)
    # our own reader gives the same cells and geometry
    m = read_nav2(yml)
    assert np.array_equal(m.occupancy, expect)
    assert m.geometry == geom
    ism = m.ism(layer="prior")
    assert ism.encoding == "occupancy_i8" and np.array_equal(ism.array(), expect)
    # 2x2 blocks of the 4x3 grid: four, one of them (row 2, columns 0-1) all unknown
    chunks = m.ism_chunks(max_side=2, layer="prior")
    assert len(chunks) == 3 and all(c.width <= 2 and c.height <= 2 for c in chunks)
    assert (chunks[2].width, chunks[2].height) == (2, 1)
    corner = geom.subgrid(2, 2, 2, 1).origin
    assert (chunks[2].origin.x, chunks[2].origin.y) == (pytest.approx(corner.x),
                                                        pytest.approx(corner.y))
    assert np.array_equal(chunks[2].array(), expect[2:3, 2:4])


def test_read_nav2_scale_mode_negate_and_errors(tmp_path: Path) -> None:
    img = np.array([[0, 255, 128]], dtype=np.uint8)  # top row only
    (tmp_path / "m.pgm").write_bytes(b"P5\n3 1\n255\n" + img.tobytes())
    (tmp_path / "m.yaml").write_text(
        "image: m.pgm\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: scale\n")
    m = read_nav2(tmp_path / "m.yaml")
    # negate: white is occupied; 128 -> occ 0.502 -> (0.502-0.196)/(0.65-0.196)*100 = 67
    assert m.occupancy.tolist() == [[0, 100, round((128 / 255 - 0.196) / (0.65 - 0.196) * 100)]]
    (tmp_path / "bad.yaml").write_text("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n")
    with pytest.raises(Nav2MapError) as e:
        read_nav2(tmp_path / "bad.yaml")
    assert e.value.code == "non_positive_resolution"
    (tmp_path / "noimg.yaml").write_text("image: nope.pgm\nresolution: 1\norigin: [0, 0, 0]\n")
    with pytest.raises(Nav2MapError) as e:
        read_nav2(tmp_path / "noimg.yaml")
    assert e.value.code == "not_found"


# -- ROS bags -------------------------------------------------------------------------------
def _ros1_typestore() -> Any:
    from rosbags.typesys import get_types_from_msg

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                   "tf2_msgs/msg/TFMessage"))
    return ts


def _header(ts: Any, frame: str, t: float) -> object:
    T = ts.types
    sec = int(t)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))
    if "seq" in dict(ts.fielddefs["std_msgs/msg/Header"][1]):  # ROS 1
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _tf_msg(ts: Any, parent: str, child: str, x: float, y: float, yaw: float,
            t: float) -> object:
    T = ts.types
    return T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, parent, t), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                       w=math.cos(yaw / 2))))])


def _scan(ts: Any, t: float) -> object:
    T = ts.types
    return T["sensor_msgs/msg/LaserScan"](
        header=_header(ts, "robot1/laser", t), angle_min=-0.5, angle_max=0.5,
        angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
        ranges=np.array([1.0, 0.05, 12.0], dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32))


def _grid(ts: Any, t: float) -> object:
    T = ts.types
    return T["nav_msgs/msg/OccupancyGrid"](
        header=_header(ts, "map", t),
        info=T["nav_msgs/msg/MapMetaData"](
            map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=0.05,
            width=2, height=2, origin=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=3.0, y=4.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))),
        data=np.array([0, 100, -1, 42], dtype=np.int8))


def _write_bag(path: Path, ros1: bool) -> None:
    """A small bag with rosbags' own writer: static + dynamic TF, two scans, one grid."""
    ts = _ros1_typestore() if ros1 else TS
    records = [
        ("/tf_static", "tf2_msgs/msg/TFMessage", 1.0,
         _tf_msg(ts, "robot1/base_link", "robot1/laser", 0.2, 0.0, 0.0, 0.0)),
        ("/scan", "sensor_msgs/msg/LaserScan", 1.5, _scan(ts, 1.5)),  # before any map pose
        ("/tf", "tf2_msgs/msg/TFMessage", 2.0,
         _tf_msg(ts, "map", "robot1/base_link", 1.0, 2.0, math.pi / 2, 2.0)),
        ("/scan", "sensor_msgs/msg/LaserScan", 2.5, _scan(ts, 2.5)),
        ("/ism/robot1/floor", "nav_msgs/msg/OccupancyGrid", 3.0, _grid(ts, 3.0)),
    ]
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(path) as w1:
            conns = {}
            for topic, typ, t, msg in records:
                if topic not in conns:
                    conns[topic] = w1.add_connection(topic, typ, typestore=ts)
                w1.write(conns[topic], int(t * 1e9), ts.serialize_ros1(msg, typ))
    else:
        from rosbags.rosbag2 import Writer as Writer2

        with Writer2(path, version=9) as w2:
            conns = {}
            for topic, typ, t, msg in records:
                if topic not in conns:
                    conns[topic] = w2.add_connection(topic, typ, typestore=ts)
                w2.write(conns[topic], int(t * 1e9), ts.serialize_cdr(msg, typ))


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_rosbag_scans_with_tf_poses_and_grids(tmp_path: Path, ros1: bool) -> None:
    bag = tmp_path / ("b.bag" if ros1 else "b")
    _write_bag(bag, ros1)
    with BagReader(bag) as reader:
        assert len(reader) == reader.total == 5
        items = list(reader)
        stats = reader.stats
    assert stats.messages == 5 and stats.unlocalized == 1 and stats.transforms == 2
    scans = [i for i in items if isinstance(i, BagScan)]
    grids = [i for i in items if isinstance(i, BagGrid)]
    assert len(scans) == 1 and len(grids) == 1
    s = scans[0]
    assert s.position == 4 and s.topic == "/scan" and s.scan.stamp == pytest.approx(2.5)
    expect = Pose2D(1.0, 2.0, math.pi / 2).compose(Pose2D(0.2, 0.0, 0.0))
    assert (s.scan.pose.x, s.scan.pose.y) == (pytest.approx(expect.x), pytest.approx(expect.y))
    assert s.scan.pose.yaw == pytest.approx(math.pi / 2)
    assert s.scan.angles.tolist() == pytest.approx([-0.5, 0.0, 0.5])
    assert s.scan.max_range == 10.0
    r = s.scan.ranges
    assert r[0] == 1.0 and math.isnan(r[1]) and r[2] == 12.0  # below range_min dropped
    g = grids[0]
    assert (g.layer, g.ism.robot, g.position) == ("robot1/floor", "robot1", 5)
    assert g.ism.resolution == 0.05 and (g.ism.origin.x, g.ism.origin.y) == (3.0, 4.0)
    assert g.ism.array().tolist() == [[0, 100], [-1, 42]]


@pytest.mark.integration
def test_replay_rosbag_fuses_the_scan_and_the_grid(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from sogm_service.apps import replay

    bag = tmp_path / "b"
    _write_bag(bag, ros1=False)
    png = tmp_path / "bag.png"
    assert replay.main(["rosbag", str(bag), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "replayed 2 scans" in out and "2 ISMs fused" in out  # 1 localised scan + 1 grid
    assert "unlocalized scans 1" in out and png.stat().st_size > 0


@pytest.mark.integration
def test_export_then_import_nav2_through_real_servers(tmp_path: Path) -> None:
    """``export nav2`` of a served map, read back as map_server does; ``import nav2`` of it
    into a second server gives the same trinary cells."""
    from sogm_service.apps import nav2tool
    from sogm_service.client import MapClient, Pose2D
    from tests.conftest import start_server, wait_processed

    cells = np.zeros((40, 60), np.int8)
    cells[10:30, 20:40] = 100
    cells[:, :5] = -1
    first = start_server(tmp_path, name="first")
    second = start_server(tmp_path, name="second")
    try:
        with MapClient.connect(first.endpoint) as client:
            client.publish_ism("ism/mapper/laser/walls", cells, resolution=0.05,
                               origin=Pose2D(0.0, 0.0, 0.0))
            wait_processed(client, 1)
        out = tmp_path / "nav2"
        assert nav2tool.export_main(["nav2", "--out", str(out), "--connect", first.endpoint,
                                     "--box", "0", "0", "3", "2"]) == 0
        doc = yaml.safe_load((out / "map.yaml").read_text())
        assert doc["resolution"] == 0.05 and doc["origin"][:2] == [0.0, 0.0]
        px = _read_pgm(out / doc["image"])
        trinary = np.flipud(_map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"],
                                                doc["negate"]))  # image top = largest y
        want = np.where(cells == 100, 100, np.where(cells == 0, 0, -1)).astype(np.int8)
        assert np.array_equal(trinary, want)
        assert nav2tool.import_main(["nav2", str(out / "map.yaml"), "--layer", "prior/walls",
                                     "--connect", second.endpoint]) == 0
        with MapClient.connect(second.endpoint) as client:
            wait_processed(client, 1)
            got = client.submap(x=1.5, y=1.0, width=3.0, height=2.0, resolution=0.05,
                                layers=["prior/walls"], interp="nearest")
        p = got.probabilities()[0]
        assert np.array_equal(np.where(p > 0.6, 100, np.where(p < 0.4, 0, -1)), want)
    finally:
        assert first.terminate() == 0 and second.terminate() == 0
