"""nav2's filter masks from the semantic layers (adapters/ros2/filters) and CostmapFilterInfo's
CDR (adapters/ros2/filterinfo), the ROS side of the CDR built with rosbags from the definition.

Expected masks are written out by hand from the rule: keepout 100 at or above the threshold,
0 observed below it, -1 never observed; speed the lowest limit at or above the threshold, 0
elsewhere.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")  # the [ros2] extra
pytest.importorskip("xxhash")

from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from sogm_service.adapters.ros2.filterinfo import (  # noqa: E402
    FilterInfoFields,
    decode_filter_info,
    encode_filter_info,
)
from sogm_service.adapters.ros2.filters import (  # noqa: E402
    FilterSpec,
    filter_masks,
    fixed_threshold,
    keepout_cells,
    speed_cells,
)
from sogm_service.adapters.ros2.keys import TYPE_HASHES  # noqa: E402
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice  # noqa: E402
from sogm_service.core.map.tiles import TiledMap  # noqa: E402

INFO = "nav2_msgs/msg/CostmapFilterInfo"


def _put(tiled: TiledMap, layer: str, value: int, x: int, y: int, stamp: float = 0.0) -> None:
    tiled.fuse(layer, np.array([[value]], dtype=np.int16),
               GridGeometry(1.0, 1, 1, Pose2D(float(x), float(y), 0.0)), stamp=stamp)


def test_threshold_in_fixed_log_odds() -> None:
    t = fixed_threshold(0.6)
    assert 1 / (1 + math.exp(-t / 1000)) >= 0.6 > 1 / (1 + math.exp(-(t - 1) / 1000))
    for bad in (0.5, 0.2, 1.0):
        with pytest.raises(ValueError):
            fixed_threshold(bad)


def test_keepout_is_100_at_the_threshold_0_below_and_minus_1_unobserved() -> None:
    t = fixed_threshold(0.6)
    planes = np.array([[[t, t - 1, 0, -3000]],
                       [[0, 0, 0, 0]]], np.int16)
    assert keepout_cells(planes, 0.6).tolist() == [[100, 0, -1, 0]]
    # a second class: the most occupied class decides (max over the classes)
    planes[1, 0, 2] = t + 5
    planes[1, 0, 3] = 2000
    assert keepout_cells(planes, 0.6).tolist() == [[100, 0, 100, 100]]
    assert keepout_cells(np.zeros((0, 2, 3), np.int16), 0.6).tolist() == [[-1] * 3] * 2


def test_speed_takes_the_lowest_limit_and_no_limit_elsewhere() -> None:
    t = fixed_threshold(0.7)
    planes = np.array([[[t, t, t - 1, 0, -2000]],
                       [[t + 9, 0, t, 0, 3000]]], np.int16)
    assert speed_cells(planes, [40, 25], 0.7).tolist() == [[25, 40, 25, 0, 25]]
    assert speed_cells(planes, [25, 40], 0.7).tolist() == [[25, 25, 40, 0, 40]]
    with pytest.raises(ValueError):
        speed_cells(planes, [0, 40], 0.7)  # 0 is nav2's "no limit", not a limit


def test_masks_from_a_map_read_classes_and_fade_with_a_forgetting_layer() -> None:
    tiled = TiledMap("m", "map", TileLattice(1.0, 16))
    tiled.set_forget({"*/person": 1.0})
    _put(tiled, "robot1/person", 3000, 1, 0, stamp=100.0)  # P 0.95
    _put(tiled, "robot2/person", -2000, 2, 0, stamp=100.0)  # seen: nobody there
    _put(tiled, "robot2/person", 300, 3, 0, stamp=100.0)
    _put(tiled, "robot1/person", 300, 3, 0, stamp=100.0)  # two robots' weak evidence adds up
    _put(tiled, "robot1/pallet", 2500, 5, 0, stamp=100.0)
    _put(tiled, "robot2/cart", 2500, 5, 0, stamp=100.0)
    _put(tiled, "robot2/cart", 2500, 6, 0, stamp=100.0)
    _put(tiled, "robot1/walls", 4000, 7, 0, stamp=100.0)
    spec = FilterSpec(keepout=("*/person", "nobody/*"), speed={"*/pallet": 40, "*/cart": 70})
    window = GridGeometry(1.0, 8, 1, Pose2D(0.0, 0.0, 0.0))
    masks = filter_masks(tiled, window, spec, stamp=5.0)
    assert set(masks) == {"keepout", "speed"}
    keep, speed = masks["keepout"], masks["speed"]
    assert keep.data.tolist() == [[-1, 100, 0, 100, -1, -1, -1, -1]]
    assert speed.data.tolist() == [[0, 0, 0, 0, 0, 40, 70, 0]]
    assert (keep.width, keep.height, keep.position, keep.frame, keep.stamp) == \
        (8, 1, (0.0, 0.0, 0.0), "map", 5.0)
    # the map's clock moves on (a later ISM of a layer that does not forget)
    _put(tiled, "robot1/walls", 10, 7, 0, stamp=103.0)  # 3 half-lives: 3000 -> 375, P 0.59
    assert filter_masks(tiled, window, spec)["keepout"].data.tolist() == \
        [[-1, 0, 0, 0, -1, -1, -1, -1]]
    _put(tiled, "robot1/walls", 10, 7, 0, stamp=120.0)  # 20 half-lives: nothing is left
    assert filter_masks(tiled, window, spec)["keepout"].data.tolist() == [[-1] * 8]
    assert filter_masks(tiled, window, spec)["speed"].data.tolist() == \
        [[0, 0, 0, 0, 0, 40, 70, 0]]  # pallets and carts do not forget
    assert filter_masks(tiled, window, FilterSpec()) == {}
    only_speed = filter_masks(tiled, window, FilterSpec(speed={"*/cart": 70}))
    assert set(only_speed) == {"speed"}


def test_filter_info_round_trips_and_reads_as_rosbags_reads_the_definition() -> None:
    ts = get_typestore(Stores.ROS2_JAZZY)  # the ROS side, from the definition text
    ts.register(get_types_from_msg("std_msgs/Header header\nuint8 type\n"
                                   "string filter_mask_topic\nfloat32 base\n"
                                   "float32 multiplier\n", INFO))
    assert TYPE_HASHES[INFO] == ts.hash_rihs01(INFO)
    info = FilterInfoFields("map", 12.5, 1, "/sogm/m/speed_mask", 0.0, 1.0)
    raw = encode_filter_info(info)
    m: Any = ts.deserialize_cdr(raw, INFO)
    assert (m.type, m.filter_mask_topic, m.base, m.multiplier, m.header.frame_id) == \
        (1, "/sogm/m/speed_mask", 0.0, 1.0, "map")
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (12, 500_000_000)
    assert decode_filter_info(raw) == info
    assert info.same_content(FilterInfoFields("map", 99.0, 1, "/sogm/m/speed_mask", 0.0, 1.0))
    assert not info.same_content(FilterInfoFields("map", 12.5, 0, "/sogm/m/speed_mask",
                                                  0.0, 1.0))


def map_server_scale(px: np.ndarray, occupied: float, free: float) -> np.ndarray:
    """nav2 map_server's scale rule for an opaque grey image (negate 0), written out."""
    occ = 1.0 - px / 255.0
    out = np.rint((occ - free) / (occupied - free) * 100.0).astype(np.int16)
    out[occ > occupied] = 100
    out[occ < free] = 0
    return out.astype(np.int8)


def test_masks_written_as_nav2_map_files_read_back_as_map_server_reads_them(
        tmp_path: Any) -> None:
    import yaml

    from sogm_service.adapters.nav2 import MASK_MODES, export_mask, read_nav2
    from tests.unit.adapters.test_nav2 import map_server_trinary, read_pgm

    geom = GridGeometry(0.05, 5, 2, Pose2D(-1.0, 2.0, 0.0))
    keep = np.array([[100, 0, -1, 100, 0], [-1, -1, 0, 100, 100]], np.int8)
    speed = np.array([[0, 40, 1, 99, 100], [7, 13, 0, 55, 33]], np.int8)
    for mask, cells in (("keepout", keep), ("speed", speed)):
        yml, _ = export_mask(tmp_path, cells, geom, mode=MASK_MODES[mask], name=f"{mask}_mask")
        doc = yaml.safe_load(yml.read_text())
        assert doc["mode"] == MASK_MODES[mask] and doc["origin"] == [-1.0, 2.0, 0.0]
        px = np.flipud(read_pgm(tmp_path / doc["image"]))  # image top row = largest y
        if mask == "keepout":
            got = map_server_trinary(px, doc["occupied_thresh"], doc["free_thresh"], 0)
        else:
            assert (doc["occupied_thresh"], doc["free_thresh"]) == (1.0, 0.0)
            got = map_server_scale(px, doc["occupied_thresh"], doc["free_thresh"])
        assert np.array_equal(got, cells), mask
        assert np.array_equal(read_nav2(yml).occupancy, cells)
    with pytest.raises(ValueError):
        export_mask(tmp_path, np.array([[50]], np.int8), GridGeometry(0.05, 1, 1,
                    Pose2D(0, 0, 0)), mode="trinary", name="bad")


def test_options_parse_and_the_viewer_paints_the_masks_over_the_map() -> None:
    pytest.importorskip("cv2")
    from sogm_service.adapters.ros2.filters import parse_speed, spec_from_options
    from sogm_service.apps.viewer.pictures import KEEPOUT_BGR, SPEED_BGR, mask_image
    from sogm_service.apps.viewer.tiles import parse_view

    assert parse_speed("*/pallet=40,robot1/cart=70") == {"*/pallet": 40, "robot1/cart": 70}
    for bad in ("*/pallet", "=40", "*/pallet=0", "*/pallet=101", "*/pallet=x"):
        with pytest.raises(ValueError):
            parse_speed(bad)
    with pytest.raises(ValueError):
        spec_from_options("*/person", 0.5, None, 0.6)
    spec = spec_from_options("*/person", 0.6, "*/pallet=40", 0.6)
    assert spec.keepout == ("*/person",) and dict(spec.speed) == {"*/pallet": 40}
    view = parse_view({"xmin": 0, "ymin": 0, "xmax": 1, "ymax": 1, "px_per_m": 10,
                       "mode": "keepout"}, ["robot1/person"])
    assert view.signature() == "keepout"
    # 1 x 3 cells: a person (P 0.95), a pallet (P 0.92), a wall; row 0 of the map
    layers = ["robot1/person", "robot1/pallet", "robot1/walls"]
    data = np.zeros((3, 1, 3), np.int16)
    data[0, 0, 0], data[1, 0, 1], data[2, 0, 2] = 2944, 2500, 4000
    keep = mask_image(data, layers, spec, "keepout")
    speed = mask_image(data, layers, spec, "speed")
    plain = mask_image(data, layers, FilterSpec(), "keepout")  # no mask asked: the map alone
    assert keep.shape == speed.shape == plain.shape == (1, 3, 3)

    def towards(img: np.ndarray, k: int, colour: np.ndarray) -> bool:
        d0 = np.abs(plain[0, k].astype(float) - colour).sum()
        return bool(np.abs(img[0, k].astype(float) - colour).sum() < 0.5 * d0)
    assert towards(keep, 0, KEEPOUT_BGR) and not towards(keep, 1, KEEPOUT_BGR)
    assert np.array_equal(keep[0, 1:], plain[0, 1:])
    assert towards(speed, 1, SPEED_BGR) and np.array_equal(speed[0, [0, 2]], plain[0, [0, 2]])
