"""The inputs of the segmentation evaluation: a scene (an SOGM stack and its ground truth), the
label images algorithms produce, the ground-truth segments, and the simulated table-top scene
(:mod:`sogm_service.eval.segmentation` runs the evaluation, :mod:`sogm_service.eval.figures` draws
it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

Labels = npt.NDArray[np.int32]
"""A segmentation: one segment number per cell, ``(H, W)``."""


@dataclass(frozen=True, slots=True)
class Scene:
    """One evaluation input: SOGM stack ``(N, H, W)`` in [0, 1] and its ground truth."""

    name: str
    layers: tuple[str, ...]
    stack: npt.NDArray[np.float32]
    classes: npt.NDArray[np.uint8]
    class_names: tuple[str, ...]
    segments: Labels  # ground-truth segments for UE and BR: see gt_segments

    @classmethod
    def build(cls, name: str, layers: Sequence[str], stack: npt.ArrayLike,
              classes: npt.ArrayLike, class_names: Sequence[str]) -> Scene:
        """A scene with its segments derived from the classes; the stack clipped to [0, 1]."""
        st = np.clip(np.asarray(stack, np.float32), 0.0, 1.0)
        cl = np.asarray(classes, np.uint8)
        if st.ndim != 3 or st.shape[1:] != cl.shape:
            raise ValueError(f"stack {st.shape} does not match classes {cl.shape}")
        return cls(name, tuple(layers), st, cl, tuple(class_names), gt_segments(cl))


def gt_segments(classes: npt.ArrayLike) -> Labels:
    """Ground-truth segments: the 4-connected components of every class, numbered 0..G-1."""
    cls = np.asarray(classes)
    out = np.zeros(cls.shape, np.int32)
    offset = 0
    for c in np.unique(cls):
        n, comp = cv2.connectedComponents((cls == c).astype(np.uint8), connectivity=4)
        mask = comp > 0
        out[mask] = comp[mask] + offset - 1
        offset += n - 1
    return out


def tabletop_scene(seed: int) -> Scene:
    """A paper-like table-top room (sim package) mapped by simulated laser + camera."""
    from sogm_service.sim.offline import map_world
    from sogm_service.sim.worlds import tabletop_world

    world = tabletop_world(seed)
    layers, stack = map_world(world, seed)
    return Scene.build(f"scene{seed}", layers, stack, world.labels, world.classes)
