"""Coarse windows are gathered (core/map/gather): only the cells each output cell
interpolates from are read, with the full path's results, and priced at what they read."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice, window_geometry
from sogm_service.core.map import footprint as fp
from sogm_service.core.map import gather
from sogm_service.core.map.tiles import TiledMap
from sogm_service.core.resample import INTERPOLATIONS, Interp, resample_stack
from tests.conftest import spy_mosaics

LO, HI = logodds.clamp_limits()


def box_of(tiled: TiledMap, window: GridGeometry) -> tuple[int, int, int, int]:
    """The map-cell box the full path of ``sample`` builds (one cell of margin)."""
    res = tiled.lattice.resolution
    xmin, ymin, xmax, ymax = window.bounds()
    c0, r0 = math.floor(xmin / res) - 1, math.floor(ymin / res) - 1
    return c0, r0, math.ceil(xmax / res) + 1 - c0, math.ceil(ymax / res) + 1 - r0


def full_path(tiled: TiledMap, window: GridGeometry, ids: list[int], interp: Interp,
              now: float | None = None) -> np.ndarray:
    """``sample``'s full path, whatever the window: the whole box, then the warp."""
    c0, r0, w, h = box = box_of(tiled, window)
    res = tiled.lattice.resolution
    src = tiled.mosaic(box, ids, now)
    return resample_stack(src, GridGeometry(res, w, h, Pose2D(c0 * res, r0 * res, 0.0)),
                          window, interp)


def random_map(seed: int, forgetting: bool, tile: int = 32) -> TiledMap:
    """Tiles of random log-odds (the whole clamp range: the steepest neighbours) in
    ``[-8, 8) x [-8, 8)`` tiles, about half of them present, stamps 0..50 s."""
    rng = np.random.default_rng(seed)
    tiled = TiledMap("m", "map", TileLattice(0.05, tile))
    if forgetting:
        tiled.set_forget({"b": 20.0})
    names = ["a", "b"]
    for i in range(-8, 8):
        for j in range(-8, 8):
            if rng.random() < 0.5:
                stack = rng.integers(LO, HI + 1, (2, tile, tile)).astype(np.int16)
                stamp = float(rng.uniform(0, 50))
                decay = {"b": stamp - float(rng.uniform(0, 30))} if forgetting else None
                tiled.insert_tile((i, j), names, stack, stamp, True, decay)
    tiled.advance_clock(60.0)
    return tiled


def random_window(rng: np.random.Generator) -> GridGeometry:
    """Rotated or not, offset, 2x..40x coarser than the map, often partly outside it (the
    map spans +-12.8 m)."""
    scale = float(rng.uniform(2, 40))
    if rng.random() < 0.3:
        scale = float(round(scale))  # whole multiples: nearest meets exact ties
    res = 0.05 * scale
    w, h = (int(v) for v in rng.integers(1, 30, 2))
    x, y = (float(v) for v in rng.uniform(-20, 20, 2))
    yaw = 0.0 if rng.random() < 0.3 else float(rng.uniform(-math.pi, math.pi))
    if yaw == 0.0:
        x, y = round(x / 0.05) * 0.05, round(y / 0.05) * 0.05
    return window_geometry(x, y, yaw, w * res, h * res, res)


@pytest.mark.parametrize("forgetting", [False, True])
@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_gather_equals_the_full_path(interp: Interp, forgetting: bool) -> None:
    tiled = random_map(11 if forgetting else 7, forgetting)
    rng = np.random.default_rng(3)
    ids = [0, 1]
    for _ in range(60):
        window = random_window(rng)
        now = None if rng.random() < 0.5 else float(rng.uniform(40, 200))
        want = full_path(tiled, window, ids, interp, now)
        got = tiled.gather(window, ids, box_of(tiled, window), interp, now)
        assert got.shape == want.shape and got.dtype == np.int16
        diff = np.abs(got.astype(np.int32) - want.astype(np.int32))
        if interp == "nearest":
            assert np.array_equal(got, want)
        else:
            assert diff.max() <= 1, (window, int(diff.max()))
    # the windows did hit the map (not a comparison of zeros)
    assert np.count_nonzero(tiled.sample(window_geometry(0, 0, 0.3, 20, 20, 0.5), ["a"]))


def test_forgetting_is_applied_on_read() -> None:
    """A decaying layer gathered at a later time is decayed exactly as the full path's."""
    tiled = TiledMap("m", "map", TileLattice(0.05, 32))
    tiled.set_forget({"b": 10.0})
    stack = np.full((2, 32, 32), 4000, dtype=np.int16)
    tiled.insert_tile((0, 0), ["a", "b"], stack, 0.0, True)
    window = window_geometry(0.8, 0.8, 0.0, 1.6, 1.6, 0.4)  # 4 x 4 cells inside the tile
    for now in (0.0, 10.0, 30.0):
        got = tiled.sample(window, ["a", "b"], "nearest", now)
        assert np.all(got[0] == 4000)
        assert np.all(got[1] == np.trunc(4000 * 0.5 ** (now / 10.0)))


def test_large_box_agrees_bit_for_bit_with_opencvs_float32_positions() -> None:
    """In a 4000-cell box float32 positions round to ~2.4e-4 cell: the gather reproduces
    OpenCV's own positions (found by the probe), so biodds still agrees."""
    if gather.float32_mode() is None:
        pytest.skip("no known float32 position mode matches this OpenCV build")
    rng = np.random.default_rng(5)
    tiled = TiledMap("m", "map", TileLattice(0.05, 64))
    for index in [(-31, -31), (-31, 30), (30, -31), (30, 30), (0, 0), (5, -9)]:
        tiled.insert_tile(index, ["a"], rng.integers(LO, HI + 1, (1, 64, 64)).astype(np.int16),
                          0.0, True)
    for yaw in (0.0, 0.7, -2.1):
        window = window_geometry(0.0, 0.0, yaw, 190.0, 190.0, 2.0)
        for interp in INTERPOLATIONS:
            want = full_path(tiled, window, [0], interp)
            got = tiled.sample(window, ["a"], interp)
            if interp == "nearest":
                assert np.array_equal(got, want)
            else:
                assert np.abs(got.astype(np.int32) - want.astype(np.int32)).max() <= 1
            assert np.count_nonzero(want)  # the window sees the tiles


def test_the_float32_mode_reproduces_opencv_on_a_fresh_probe() -> None:
    mode = gather.float32_mode()
    if mode is None:
        pytest.skip("no known float32 position mode matches this OpenCV build")
    img = np.ascontiguousarray(np.broadcast_to((np.arange(8192) % 2).astype(np.float32),
                                               (2, 8192)))
    rng = np.random.default_rng(9)
    for _ in range(20):
        w = int(rng.integers(1, 90))
        a = rng.uniform(-60, 60)
        m = np.array([[a, rng.uniform(-1, 1), 4096.0 - a * w / 2 + rng.uniform(-50, 50)],
                      [0.0, 0.0, 0.5]])  # positions stay inside the image
        got = cv2.warpAffine(img, m, (w, 3), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        assert gather._probe_matches(mode, m, got.astype(np.float64), w, 3)


def test_sample_gathers_only_coarse_windows() -> None:
    tiled = random_map(1, False, tile=64)
    built = spy_mosaics(tiled)
    coarse = window_geometry(1.0, -2.0, 0.4, 20.0, 20.0, 1.0)  # 20x coarser
    got = tiled.sample(coarse, ["a", "b"])
    assert built == []  # no box built
    price = fp.window_price(1.0, -2.0, 0.4, 20.0, 20.0, 1.0, 0.05)
    assert price is not None and price.gathered
    assert np.abs(got.astype(np.int32) - full_path(tiled, coarse, [0, 1], "biodds")
                  .astype(np.int32)).max() <= 1
    built.clear()
    tiled.sample(window_geometry(0.3, 0.2, 0.0, 12.8, 12.8, 0.05), ["a", "b"])  # 256x256
    tiled.sample(window_geometry(0.3, 0.2, 0.5, 12.8, 12.8, 0.1), ["a", "b"])  # 2x, rotated
    assert len(built) == 2  # the full path: the gather would not read 4x fewer cells


def test_price_counts_the_cells_read() -> None:
    # the request: 400 m at 4 m cells on a 5 cm map
    for interp, taps in (("biodds", 4), ("bilinear", 4), ("nearest", 1)):
        price = fp.window_price(0.0, 0.0, 0.0, 400.0, 400.0, 4.0, 0.05, interp)
        assert price is not None and price.gathered
        assert price.mosaic_cells == 8002 * 8002
        assert price.read_cells == taps * 100 * 100 == gather.tap_count(100, 100, interp)
    # at map resolution (and 2x coarser) the box is read: the price says so
    for res in (0.05, 0.1):
        price = fp.window_price(0.0, 0.0, 0.0, 12.8, 12.8, res, 0.05)
        assert price is not None and not price.gathered
        assert price.read_cells == price.mosaic_cells
    # the rule is min(box, taps) with a margin of 4: 300 m at 0.1 m gathers 36 M = the box
    price = fp.window_price(0.0, 0.0, 0.0, 300.0, 300.0, 0.1, 0.05)
    assert price is not None and not price.gathered and price.read_cells == 6002 * 6002


# -- through a real server ----------------------------------------------------------------
