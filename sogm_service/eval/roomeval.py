"""Supercells on room maps: undersegmentation and boundary recall against SEEDS, compactness.

Part of ``sogm-service eval supercells`` (:mod:`sogm_service.eval.segmentation` calls
:func:`run_room_evaluation`):

1. **Labelled room maps** (:func:`sogm_service.eval.rooms.room_scene`, seeds ``seed, seed + 1,
   ...``): one occupancy layer, ground truth the rooms, the walls and furniture, the outside.
2. **At equal segment count.**  SEVDS's count is its initial grid's, ``ceil(H / b) ceil(W / b)``
   (a move never empties a supercell).  OpenCV's SEEDS rounds the count it is asked for to its
   own block grid, so it is asked for the count whose result lies nearest SEVDS's
   (:func:`seeds_request`).  SEEDS keeps the set of its parameter grid with the lowest scene mean
   of ``(1 - BR) + UE``; SEVDS runs with the defaults of the ``supercells`` query (no tuning),
   the default without the doorway term (``doorway = 0``), the paper's rule (``criterion =
   "distribution"``, no doorway term), the default without the extent bound (``extent = 64``)
   and the paper's rule at gamma 0.01 with 5 bins, 3 levels and no bound next to it.
3. **Compactness** of every label image (:func:`compactness`): the widest span of a segment in
   block sizes, the largest segment, the most neighbours, segments in more than one piece, and
   nodes (the cell nearest each centroid, :mod:`sogm_service.core.sevds.supercells`) or bare
   centroids that lie outside their own segment.
4. **Timing**: the mean wall time of one segmentation per map, and the process's CPU time
   (what it costs when other processes share the cores).
5. **The Intel replay** (:func:`intel_stack`: the Intel Research Lab log's 910 scans fused at
   5 cm into one ``obstacle`` layer, the window around every pose with 8 m of margin), no
   labels: compactness, node evidence and the best of three wall times per variant
   (:func:`intel_rows`).

Outputs: ``rooms.csv`` (every algorithm, map and block) and the markdown of
:func:`rooms_markdown`.
"""

from __future__ import annotations

import csv
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core.sevds.segment import SevdsParams, sevds
from sogm_service.core.sevds.supercells import adjacency, nearest_cells
from sogm_service.eval import metrics
from sogm_service.eval.rooms import room_scene
from sogm_service.eval.scenes import Labels, Scene

Params = dict[str, float | int | str]
ROOM_BLOCKS: tuple[int, ...] = (8, 16)
SEEDS_GRID: tuple[Params, ...] = tuple(
    {"levels": lv, "prior": pr, "bins": b} for lv in (3, 4) for pr in (0, 2, 5) for b in (3, 5, 8))
SEEDS_QUICK: tuple[Params, ...] = ({"levels": 4, "prior": 0, "bins": 3},)
SEVDS_VARIANTS: dict[str, SevdsParams] = {
    "SEVDS (defaults)": SevdsParams(),
    "SEVDS (no doorway term)": SevdsParams(doorway=0.0),
    "SEVDS (paper rule)": SevdsParams(criterion="distribution", doorway=0.0),
    "SEVDS (no extent bound)": SevdsParams(extent=64.0),
    "SEVDS (paper rule, gamma 0.01, bins 5, levels 3, no bound)": SevdsParams(
        levels=3, bins=5, gamma=0.01, criterion="distribution", extent=64.0, doorway=0.0),
}


def _to_u8(stack: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
    return np.ascontiguousarray(np.rint(stack.transpose(1, 2, 0) * 255.0).astype(np.uint8))


@functools.lru_cache(maxsize=256)
def seeds_request(height: int, width: int, channels: int, levels: int, target: int) -> int:
    """The count to ask OpenCV's SEEDS for so that it makes the number of superpixels nearest
    ``target`` (it rounds every request to its own block grid); the smallest such request."""
    best: tuple[int, int] | None = None
    for req in range(max(1, target // 2), 4 * target + 1, max(1, target // 64)):
        s = cv2.ximgproc.createSuperpixelSEEDS(width, height, channels, req, levels, 0, 2, False)
        n = int(s.getNumberOfSuperpixels())
        if best is None or abs(n - target) < abs(best[1] - target):
            best = (req, n)
        if n > target + target // 8:
            break
    assert best is not None
    return best[0]


def run_seeds(stack: npt.NDArray[np.float32], target: int, p: Params) -> Labels:
    """OpenCV's SEEDS at (about) ``target`` superpixels, 4 iterations."""
    img = _to_u8(stack)
    h, w, c = img.shape
    req = seeds_request(h, w, c, int(p["levels"]), target)
    seeds = cv2.ximgproc.createSuperpixelSEEDS(w, h, c, req, int(p["levels"]), int(p["prior"]),
                                               int(p["bins"]), False)
    seeds.iterate(img, 4)
    return np.asarray(seeds.getLabels(), np.int32)


def compactness(labels: npt.ArrayLike, block: int) -> dict[str, float]:
    """The compactness figures of module docstring item 3 for one label image."""
    lab = np.asarray(labels)
    dense = np.unique(lab.ravel(), return_inverse=True)[1].reshape(lab.shape).astype(np.int32)
    count = int(dense.max()) + 1
    flat = dense.ravel()
    v, u = np.divmod(np.arange(flat.size), lab.shape[1])
    box = []
    for axis in (v, u):
        lo = np.full(count, np.iinfo(np.int64).max)
        hi = np.full(count, -1)
        np.minimum.at(lo, flat, axis)
        np.maximum.at(hi, flat, axis)
        box += [lo, hi + 1]
    span = np.maximum(box[1] - box[0], box[3] - box[2])
    areas = np.bincount(flat, minlength=count)
    edges = adjacency(dense)
    degree = np.bincount(edges.ravel(), minlength=count) if edges.size else np.zeros(count)
    pieces = 0
    for k in range(count):  # within each segment's bounding box
        crop = dense[box[0][k]:box[1][k], box[2][k]:box[3][k]] == k
        n, _ = cv2.connectedComponents(crop.astype(np.uint8), connectivity=4)
        pieces += int(n > 2)  # the background and more than one piece
    cu = np.bincount(flat, u, count) / areas
    cv = np.bincount(flat, v, count) / areas
    centroid_cell = dense[np.clip(np.rint(cv), 0, lab.shape[0] - 1).astype(int),
                          np.clip(np.rint(cu), 0, lab.shape[1] - 1).astype(int)]
    node = nearest_cells(dense, np.stack([cu, cv], axis=1))
    return {"max_extent_blocks": float(span.max() / block), "max_area": float(areas.max()),
            "max_neighbours": float(degree.max()), "split_segments": float(pieces),
            "centroids_outside": float(np.count_nonzero(centroid_cell != np.arange(count))),
            "nodes_outside": float(np.count_nonzero(dense[node[:, 1], node[:, 0]]
                                                    != np.arange(count)))}


def _row(alg: str, scene: Scene, block: int, labels: Labels, seconds: tuple[float, float],
         params: str) -> dict[str, Any]:
    """UE, BR and the time; :func:`_compact` adds the compactness of the rows kept."""
    return {"algorithm": alg, "map": scene.name, "block": block,
            "superpixels": len(np.unique(labels)), "params": params,
            "ue": metrics.undersegmentation_error(labels, scene.segments),
            "br": metrics.boundary_recall(labels, scene.segments), "seconds": seconds[0],
            "cpu_seconds": seconds[1], "labels": labels}


def _compact(row: dict[str, Any]) -> dict[str, Any]:
    labels = row.pop("labels")
    return {**row, **compactness(labels, int(row["block"]))}


def _timed(run: Callable[[], Labels]) -> tuple[Labels, tuple[float, float]]:
    """The labels, the wall time and the process's CPU time (what the run cost when other
    processes share the cores)."""
    t, c = time.perf_counter(), time.process_time()
    labels = run()
    return labels, (time.perf_counter() - t, time.process_time() - c)


def run_room_evaluation(maps: int = 4, seed: int = 0, blocks: Sequence[int] = ROOM_BLOCKS,
                        scene_factory: Callable[[int], Scene] | None = None,
                        step: Callable[[str], None] | None = None,
                        seeds_grid: Sequence[Params] = SEEDS_GRID) -> list[dict[str, Any]]:
    """Rows of module docstring items 2-4: every SEVDS variant and SEEDS tuned over
    ``seeds_grid`` per map and block.  ``step`` is told after each algorithm and block (a
    progress bar)."""
    make = scene_factory or room_scene
    scenes = [make(seed + k) for k in range(maps)]
    sevds(scenes[0].stack, SevdsParams())  # compile (or load) the kernels outside the timing
    rows: list[dict[str, Any]] = []
    for block in blocks:
        for name, base in SEVDS_VARIANTS.items():
            p = replace(base, block_size=block)
            for sc in scenes:
                lab, dt = _timed(lambda sc=sc, p=p: sevds(sc.stack, p).labels)  # type: ignore[misc]
                rows.append(_compact(_row(name, sc, block, lab, dt, f"criterion={p.criterion} "
                                          f"gamma={p.gamma} extent={p.extent}")))
            if step:
                step(f"rooms {name} block {block}")
        best: tuple[float, list[dict[str, Any]]] | None = None
        for sp in seeds_grid:
            cand = []
            for sc in scenes:
                n, h, w = sc.stack.shape
                target = -(-h // block) * -(-w // block)
                seeds_request(h, w, n, int(sp["levels"]), target)  # the search: not timed
                lab, dt = _timed(lambda sc=sc, t=target, sp=sp: run_seeds(sc.stack, t, sp))  # type: ignore[misc]
                cand.append(_row("SEEDS (tuned)", sc, block, lab, dt,
                                 " ".join(f"{k}={v}" for k, v in sp.items())))
            score = float(np.mean([1.0 - r["br"] + r["ue"] for r in cand]))
            if best is None or score < best[0]:
                best = (score, cand)
        assert best is not None
        rows += [_compact(r) for r in best[1]]
        if step:
            step(f"rooms SEEDS block {block}")
    return rows


def _means(rows: list[dict[str, Any]]) -> dict[tuple[int, str], dict[str, float]]:
    out: dict[tuple[int, str], dict[str, float]] = {}
    for r in rows:
        out.setdefault((int(r["block"]), str(r["algorithm"])), {})
    for key in out:
        sel = [r for r in rows if (int(r["block"]), str(r["algorithm"])) == key]
        m = {k: float(np.mean([r[k] for r in sel])) for k in
             ("superpixels", "ue", "br", "seconds", "cpu_seconds", "max_neighbours",
              "split_segments",
              "centroids_outside", "nodes_outside")}
        m["max_extent_blocks"] = float(max(r["max_extent_blocks"] for r in sel))
        m["max_area"] = float(max(r["max_area"] for r in sel))
        out[key] = m
    return out


def rooms_markdown(rows: list[dict[str, Any]]) -> str:
    """Means over the maps per block and algorithm, UE and BR next to tuned SEEDS'."""
    text = ("| block | algorithm | superpixels | UE | UE / SEEDS | BR | BR - SEEDS | "
            "widest (blocks) | largest (cells) | neighbours (max) | in pieces | "
            "centroids outside | nodes outside | s per map | CPU s |\n"
            "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    means = _means(rows)
    for (block, alg), m in means.items():
        ref = means.get((block, "SEEDS (tuned)"), m)
        text += (f"| {block} | {alg} | {m['superpixels']:.0f} | {m['ue']:.4f} | "
                 f"{m['ue'] / max(ref['ue'], 1e-12):.2f} | {m['br']:.4f} | "
                 f"{m['br'] - ref['br']:+.4f} | {m['max_extent_blocks']:.2f} | "
                 f"{m['max_area']:.0f} | {m['max_neighbours']:.1f} | {m['split_segments']:.1f} | "
                 f"{m['centroids_outside']:.1f} | {m['nodes_outside']:.1f} | "
                 f"{m['seconds']:.4f} | {m['cpu_seconds']:.4f} |\n")
    return text


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def intel_stack() -> npt.NDArray[np.int16]:
    """``(1, H, W)`` fixed log-odds of the Intel replay (module docstring item 5)."""
    from sogm_service.adapters.carmen import read_carmen
    from sogm_service.adapters.laser import laser_ism
    from sogm_service.core import logodds
    from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
    from sogm_service.core.map.tiles import TiledMap
    from sogm_service.data import INTEL_LOG

    res = 0.05
    tiled = TiledMap("intel", "map", TileLattice(res, 256))
    poses = []
    for scan in read_carmen(INTEL_LOG):
        g, p = laser_ism(scan.ranges, scan.angles, scan.pose, res, min(8.0, scan.max_range),
                         device_max_range=scan.max_range)
        tiled.fuse("obstacle", logodds.increments(p, logodds.Encoding.PROB_F32, tiled.eps0), g,
                   "biodds")
        poses.append((scan.pose.x, scan.pose.y))
    xy = np.array(poses)
    lo, hi = xy.min(axis=0) - 8.0, xy.max(axis=0) + 8.0
    w, h = (int(v) for v in (hi - lo) / res)
    window = GridGeometry(res, w, h, Pose2D(float(lo[0]), float(lo[1]), 0.0))
    return tiled.sample(window, ["obstacle"])


def intel_rows(stack: npt.NDArray[np.int16], blocks: Sequence[int] = ROOM_BLOCKS,
               repeats: int = 3) -> list[dict[str, Any]]:
    """Per SEVDS variant and block: compactness, node evidence counts, best wall time."""
    from sogm_service.core.sevds.supercells import FREE, UNKNOWN, extract_supercells

    rows: list[dict[str, Any]] = []
    for block in blocks:
        for name, base in SEVDS_VARIANTS.items():
            p = replace(base, block_size=block)
            best, cpu = np.inf, np.inf
            for _ in range(repeats):
                t, c = time.perf_counter(), time.process_time()
                graph, _ = extract_supercells(stack, params=p)
                best = min(best, time.perf_counter() - t)
                cpu = min(cpu, time.process_time() - c)
            ev = graph.evidence()
            rows.append({"algorithm": name, "block": block, "superpixels": graph.count,
                         "seconds": best, "cpu_seconds": cpu,
                         **compactness(graph.labels, block),
                         "occupied": int(np.count_nonzero(ev >= 0)),
                         "free": int(np.count_nonzero(ev == FREE)),
                         "unknown": int(np.count_nonzero(ev == UNKNOWN))})
    return rows


def intel_markdown(rows: list[dict[str, Any]]) -> str:
    text = ("| block | algorithm | supercells | widest (blocks) | largest (cells) | "
            "neighbours (max) | in pieces | centroids outside | nodes outside | occupied | "
            "free | unknown | s (best of 3) | CPU s |\n"
            "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    for r in rows:
        text += (f"| {r['block']} | {r['algorithm']} | {r['superpixels']} | "
                 f"{r['max_extent_blocks']:.2f} | {r['max_area']:.0f} | "
                 f"{r['max_neighbours']:.0f} | {r['split_segments']:.0f} | "
                 f"{r['centroids_outside']:.0f} | {r['nodes_outside']:.0f} | {r['occupied']} | "
                 f"{r['free']} | {r['unknown']} | {r['seconds']:.3f} | "
                 f"{r['cpu_seconds']:.3f} |\n")
    return text
