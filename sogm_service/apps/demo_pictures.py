"""The demo's pictures and scores: each layer, the classes, Eq. 6's two fusions, the ground
truth, a rotated sub-map around each robot, the SEVDS graph, and each class's IoU."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from sogm_service.apps.demo_layers import label

PNG_LAYER_LIMIT = 16


def class_iou(world: Any, layers: list[str], probs: npt.NDArray[np.float32]) -> dict[str, float]:
    """Per layer: IoU of ``p > 0.5`` against the ground truth, over the cells it observed
    (keyed by :func:`~sogm_service.apps.demo_layers.label`: a class pattern by its class).

    ``obstacle`` (the laser's layer) is compared with everything standing on the floor; a
    camera class with the world's class of that name.  Unobserved cells (log-odds 0) are left
    out: the fleet cannot be blamed for what it never saw.
    """
    out: dict[str, float] = {}
    for k, layer in enumerate(layers):
        name = layer.rsplit("/", 1)[-1]
        if name == "obstacle":
            truth = world.occupied
        elif name in world.classes:
            truth = world.mask(name)
        else:
            continue
        p = probs[k]
        seen = np.abs(p - 0.5) > 1e-3
        pred = (p > 0.5) & seen
        gt = truth & seen
        union = np.count_nonzero(pred | gt)
        out[label(layer)] = round(float(np.count_nonzero(pred & gt) / union), 4) if union else 0.0
    return out


def world_window(world: Any) -> dict[str, Any]:
    """The query window of the whole world, at the map's resolution."""
    g = world.geometry
    w, h = g.size_m
    x, y = g.centre()
    return dict(x=x, y=y, yaw=g.origin.yaw, width=w, height=h, resolution=g.resolution)


def robot_markers(watcher: Any) -> list[tuple[str, float, float, float | None]]:
    return [(robot, pose.x, pose.y, pose.yaw) for robot, pose in sorted(watcher.poses.items())]


def write_layers(sub: Any, out: Path, robots: list[Any]) -> list[str]:
    from sogm_service.apps.render import save_classes_png, save_grid_png

    p = sub.probabilities()
    files = []
    for k, layer in enumerate(sub.layers[:PNG_LAYER_LIMIT]):
        name = f"layer_{label(layer).replace('/', '_')}.png"
        save_grid_png(out / name, p[k], sub.geometry, title=f"layer {layer}", robots=robots)
        files.append(name)
    save_classes_png(out / "classes.png", p, sub.geometry, [label(n) for n in sub.layers],
                     robots=robots)
    files.append("classes.png")
    return files


def obstacle_layers(layers: list[str]) -> list[str]:
    """The layers that say "something stands here" (all but free-space classes like floor)."""
    return [n for n in layers if n.rsplit("/", 1)[-1] not in ("floor", "free")] or layers


def write_fused(client: Any, window: dict[str, Any], layers: list[str],
                 out: Path, robots: list[Any]) -> list[str]:
    """Eq. 6 over the obstacle-like layers: P_B (same evidence from several sensors) and P_M."""
    from sogm_service.apps.render import save_grid_png

    files = []
    for method in ("bayes", "max"):
        fused = client.fused(method=method, **window, layers=layers, encoding="prob_f32")
        name = f"fused_{method}.png"
        save_grid_png(out / name, fused.probabilities(), fused.geometry,
                      title=f"fused ({method}, Eq. 6) over {', '.join(layers)}", robots=robots)
        files.append(name)
    return files


def ground_truth_image(world: Any, layers: list[str]) -> npt.NDArray[np.uint8]:
    """Ground truth in the colours ``classes.png`` gives the same class (walls as obstacle)."""
    from sogm_service.apps.render import UNKNOWN_BGR, class_colors

    palette = class_colors(len(layers))
    names = [n.rsplit("/", 1)[-1] for n in layers]
    colors = np.zeros((len(world.classes), 3), np.uint8)
    for k, cls in enumerate(world.classes):
        name = cls if cls in names else "obstacle"
        colors[k] = palette[names.index(name)] if name in names else (90, 90, 90)
    colors[0] = UNKNOWN_BGR
    return np.ascontiguousarray(colors[world.labels][::-1])


def robot_submaps(client: Any, watcher: Any, map_res: float, out: Path,
                   files: list[str], layers: list[str] | None = None) -> dict[str, float]:
    """A rotated window around each robot at 2x the map's cell size; timed queries."""
    from sogm_service.apps.render import save_classes_png

    robots = robot_markers(watcher)
    timings: list[float] = []
    res = 2 * map_res
    side = 256 * res
    for robot, pose in sorted(watcher.poses.items()):
        window = dict(x=pose.x, y=pose.y, yaw=pose.yaw, width=side, height=side, resolution=res)
        for _ in range(10):
            t0 = time.perf_counter()
            sub = client.submap(**window, layers=layers, encoding="prob_u8")
            timings.append(time.perf_counter() - t0)
        save_classes_png(out / f"submap_{robot}.png", sub.probabilities(), sub.geometry,
                         [label(n) for n in sub.layers], title=f"sub-map around {robot}",
                         robots=robots)
        files.append(f"submap_{robot}.png")
    if not timings:
        return {}
    ms = np.array(timings) * 1e3
    return {"count": len(ms), "p50": round(float(np.median(ms)), 3),
            "p99": round(float(np.percentile(ms, 99)), 3)}


def write_supercells(client: Any, world: Any, watcher: Any, out: Path,
                      files: list[str], layers: list[str] | None = None) -> int | None:
    """The SEVDS graph of a 128 x 128 cell window around the first robot, over the fused map."""
    from sogm_service.apps.render import save_graph_png

    if not watcher.poses:
        return None
    pose = watcher.poses[sorted(watcher.poses)[0]]
    res = world.geometry.resolution
    window = dict(x=pose.x, y=pose.y, yaw=0.0, width=128 * res, height=128 * res,
                  resolution=res)
    reply = client.supercells(**window, labels=True, layers=layers)
    fused = client.fused(method="max", **window, layers=obstacle_layers(reply.layers),
                         encoding="prob_f32")
    save_graph_png(out / "supercells.png", reply, fused, robots=robot_markers(watcher))
    files.append("supercells.png")
    return len(reply.nodes)
