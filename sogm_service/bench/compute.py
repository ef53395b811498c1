"""Benchmarks of the pure core: fusion (aligned and rotated), SEVDS, scan matching."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.bench.core import Row, interleaved, median, time_row, unavailable
from sogm_service.core.geometry import Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server import pipeline as ingest
from sogm_service.wire.messages import IsmMessage, PoseModel

MAP_RES = 0.05


def synthetic_ism(size: int, seed: int = 0) -> npt.NDArray[np.uint8]:
    """A ``prob_u8`` ISM that looks like a laser scan: unknown, a free area, walls, objects.

    Structured rather than random on purpose: random codes defeat branch prediction and
    caches in a way no sensor does.
    """
    rng = np.random.default_rng(seed)
    ism = np.full((size, size), 128, np.uint8)  # ~0.5: no information
    c = size // 2
    cv2.circle(ism, (c, c), int(size * 0.45), 60, -1)  # free space, p ~ 0.24
    for _ in range(12):
        x0, y0, x1, y1 = (int(v) for v in rng.integers(0, size, 4))
        cv2.line(ism, (x0, y0), (x1, y1), 235, 2)  # walls, p ~ 0.92
    for _ in range(6):
        x, y = (int(v) for v in rng.integers(0, size, 2))
        cv2.circle(ism, (x, y), int(rng.integers(3, 12)), 200, -1)
    return ism


def ism_message(codes: npt.NDArray[np.uint8], res: float, origin: Pose2D) -> IsmMessage:
    return IsmMessage(resolution=res, origin=PoseModel(x=origin.x, y=origin.y, yaw=origin.yaw),
                      width=codes.shape[1], height=codes.shape[0], encoding="prob_u8",
                      data=np.ascontiguousarray(codes).tobytes())


def fresh_map() -> TiledMap:
    return TiledMap("bench", "map", TileLattice(MAP_RES, 256))


def fuse_call(tiled: TiledMap, msg: IsmMessage) -> Callable[[], object]:
    """What the server's worker does per ISM after decoding: LUT, resample, add, clamp."""
    return lambda: ingest.fuse_ism(tiled, msg, "obstacle", "biodds")


def add_floor(cells: int) -> Callable[[], object]:
    """The anchor before: one cache-resident ``numpy.add`` of two int16 arrays."""
    rng = np.random.default_rng(1)
    a = rng.integers(-100, 100, cells).astype(np.int16)
    b = rng.integers(-100, 100, cells).astype(np.int16)
    return lambda: np.add(a, b, out=a)


def streaming_floor(codes: npt.NDArray[np.uint8]) -> Callable[[], object]:
    """The least any aligned fuse must do: read the 8-bit ISM once, read and write the int16
    cells (one add of the codes into a map-sized int16 array, in place)."""
    state = np.zeros(codes.shape, np.int16)
    return lambda: np.add(state, codes, out=state, casting="unsafe")


def fuse_aligned(quick: bool) -> Row:
    size = 1024
    codes = synthetic_ism(size)
    msg = ism_message(codes, MAP_RES, Pose2D(0.0, 0.0, 0.0))
    repeats = 20 if quick else 200
    ours, base = interleaved(fuse_call(fresh_map(), msg), streaming_floor(codes), repeats)
    row = time_row("fuse_aligned_1024", ours, base, 3.0,
                   "the streaming floor: read the u8 ISM once, read and write the int16 cells",
                   "ISM prob_u8 on the map lattice: 16 tiles of 256x256; LUT+add+clamp")
    old = interleaved(add_floor(size * size), lambda: None, repeats)[0]
    row.details["old_anchor_numpy_add_ms"] = median(old) * 1e3
    row.details.update(_aligned_bounds(msg, repeats, quick))
    row.note += (f"; of which the 8-bit LUT {row.details['lut_ms']:.3f} ms; old anchor (one "
                 f"cache-resident numpy.add) {row.details['old_anchor_numpy_add_ms']:.3f} ms")
    return row


def _aligned_bounds(msg: IsmMessage, repeats: int, quick: bool) -> dict[str, float | str]:
    """What bounds the aligned fuse: the table lookup alone, and the add floor per 1M cells
    when the arrays do not fit in the caches (64 Mi cells)."""
    from sogm_service.core import logodds

    codes = msg.array()
    lut = interleaved(lambda: logodds.increments(codes, "prob_u8"), lambda: None, repeats)[0]
    out: dict[str, float | str] = {"lut_ms": median(lut) * 1e3}
    if not quick:
        big = 1 << 26
        t = interleaved(add_floor(big), lambda: None, 5, warmup=1)[0]
        out["add_floor_uncached_ms_per_1M"] = median(t) * 1e3 * (1 << 20) / big
    return out


def fuse_rotated(quick: bool) -> Row:
    size = 512
    codes = synthetic_ism(size)
    # Origin off the lattice, 30 degrees, ISM cells 1.5x the map's: every tile needs a warp.
    rotated = ism_message(codes, 1.5 * MAP_RES, Pose2D(3.21, 2.17, math.radians(30.0)))
    aligned = ism_message(codes, MAP_RES, Pose2D(0.0, 0.0, 0.0))
    repeats = 20 if quick else 200
    ours, base = interleaved(fuse_call(fresh_map(), rotated), footprint_warp(rotated), repeats)
    row = time_row("fuse_rotated_512", ours, base, 1.5,
                   "one float32 cv2.warpAffine of the ISM's whole footprint at map resolution",
                   "30 deg, origin off the lattice, ISM cell = 1.5 map cells, biodds")
    old = interleaved(fuse_call(fresh_map(), aligned), lambda: None, repeats)[0]
    row.details["old_anchor_aligned_fuse_ms"] = median(old) * 1e3
    row.note += f"; old anchor (the same ISM fused aligned) {median(old) * 1e3:.3f} ms"
    return row


def footprint_warp(msg: IsmMessage) -> Callable[[], object]:
    """The rotated fuse's bound: one bilinear float32 warp of the ISM into the axis-aligned
    box of its footprint on the map's lattice (what every tile block together needs)."""
    from sogm_service.core import logodds
    from sogm_service.core.geometry import GridGeometry
    from sogm_service.core.resample import dst_to_src

    src_geom = GridGeometry(msg.resolution, msg.width, msg.height,
                            Pose2D(msg.origin.x, msg.origin.y, msg.origin.yaw))
    xmin, ymin, xmax, ymax = src_geom.bounds()
    c0, r0 = math.floor(xmin / MAP_RES), math.floor(ymin / MAP_RES)
    w, h = math.ceil(xmax / MAP_RES) - c0, math.ceil(ymax / MAP_RES) - r0
    box = GridGeometry(MAP_RES, w, h, Pose2D(c0 * MAP_RES, r0 * MAP_RES, 0.0))
    src = logodds.increments(msg.array(), "prob_u8").astype(np.float32)
    m = dst_to_src(src_geom, box)[:2]
    out = np.empty((h, w), np.float32)
    return lambda: cv2.warpAffine(src, m, (w, h), dst=out,
                                  flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def sevds(quick: bool) -> Row:
    from sogm_service.bench.sevds import benchmark_sevds_vs_seeds

    name, target = "sevds_256x256x3", "<= 1x"
    result = benchmark_sevds_vs_seeds((3,), height=256, width=256, repeats=2 if quick else 7)[0]
    ours_s, base_s = result.get("sevds_s"), result.get("seeds_s")
    if not isinstance(ours_s, float) or not isinstance(base_s, float):
        return unavailable(name, target, f"no timings in {result}")
    ratio = ours_s / base_s
    details = {k: v for k, v in result.items() if isinstance(v, (int, float, str))}
    return Row(name, ours_s * 1e3, base_s * 1e3, "ms", ratio, target, ratio <= 1.0,
               "OpenCV SEEDS (ximgproc), same input, levels, bins, iterations and superpixel "
               "count", f"bench.sevds.benchmark_sevds_vs_seeds, best of repeats; "
               f"{result.get('supercells')} supercells", details)


def matching(quick: bool) -> Row:
    from sogm_service.bench.matching import benchmark_match

    repeats = 3 if quick else 20
    result = benchmark_match(size=256, repeats=repeats)
    orb = _orb_detect_time(repeats)
    ours_s = result["median_s"]
    return Row("scan_match_256", ours_s * 1e3, orb * 1e3, "ms", ours_s / orb, "report", None,
               "one cv2 ORB detectAndCompute on a 256x256 image",
               f"accepted={bool(result.get('accepted'))}, inliers={result.get('inliers', 0):g}",
               {k: float(v) for k, v in result.items()})


def _orb_detect_time(repeats: int) -> float:
    img = synthetic_ism(256)
    orb = cv2.ORB.create(nfeatures=500)
    times = interleaved(lambda: orb.detectAndCompute(img, None), lambda: None, repeats)[0]
    return median(times)
