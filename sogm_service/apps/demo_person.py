"""The demo's sensors: the laser cast on the map's lattice (sharp walls) and a
moving person in a layer that forgets (:mod:`sogm_service.sim.moving`).

The person layer is reported on its own (``layer_person.png``, nav2's keepout of it in
``keepout_mask.png``, and ``summary.json``'s ``moving``); every other output is computed over
the other layers.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.apps.demo_layers import has_layer
from sogm_service.sim.moving import PersonDetector, warehouse_person
from sogm_service.sim.robots import SimStep
from sogm_service.sim.sensors import Sensor, SensorIsm, TiltedLaser, default_sensors
from sogm_service.sim.worlds import World

PERSON_LAYER = "person"
PERSON_HALF_LIFE_S = 5.0
"""Half-life of the person layer, in seconds of the ISM stamps (simulated time)."""
MOVING_LAYERS = (PERSON_LAYER,)
OLD_HALF_LIVES = 4.0
KEEPOUT_THRESHOLD = 0.6  # [nav2] keepout_threshold's default
"""A spot the person left this many half-lives ago counts as old (1/16 of its evidence)."""


def demo_sensors(world: World) -> list[Sensor]:
    """The default suite with the laser cast on the map's lattice (no resampling)."""
    return [dataclasses.replace(s, grid="lattice") if isinstance(s, TiltedLaser) else s
            for s in default_sensors(world)]


def demo_observers(world: World) -> list[Callable[[SimStep], list[SensorIsm]]]:
    """A person detector on every robot when the world has a walking person."""
    person = warehouse_person(world)
    if person is None:
        return []
    detector = PersonDetector(person, PERSON_LAYER, resolution=world.geometry.resolution)
    return [lambda step: detector.observe(world, step)]


def forgetting_config(config: Any, world: World, person: str = PERSON_LAYER) -> Any:
    """The demo's server config with the person layer forgetting and kept out of (nav2's
    keepout mask, published with ``--ros2``).  ``person``: the layer, or a pattern matching
    every robot's person layer (``*/*/person``)."""
    if warehouse_person(world) is None:
        return config
    return config.model_copy(update={
        "map": config.map.model_copy(update={"forget": {person: PERSON_HALF_LIFE_S}}),
        "nav2": config.nav2.model_copy(update={"keepout": [person]})})


def keepout_report(client: Any, world: World, out: Path, files: list[str],
                   ages: Callable[[np.ndarray], list[float]],
                   person: str = PERSON_LAYER) -> dict[str, Any]:
    """``keepout_mask.png`` (nav2's keepout of the person: red over the person layer) and how
    long ago the person was at the kept-out cells: the keepout follows the person and fades."""
    import cv2

    from sogm_service.adapters.ros2.filters import KEEP_OUT, keepout_cells
    from sogm_service.apps.render import probability_image
    from sogm_service.core import logodds

    g = world.geometry
    w, h = g.size_m
    x, y = g.centre()
    sub = client.submap(x=x, y=y, yaw=0.0, width=w, height=h, resolution=g.resolution,
                        layers=[person], encoding="logodds_i16", interp="nearest")
    fixed = np.asarray(sub.data[0], np.int16)
    mask = keepout_cells(fixed[None], KEEPOUT_THRESHOLD)
    img = probability_image(logodds.fixed_to_prob(fixed), unknown=fixed == 0)[::-1].copy()
    img[mask == KEEP_OUT] = (40, 40, 230)
    cv2.imwrite(str(out / "keepout_mask.png"), np.ascontiguousarray(img[::-1]))
    files.append("keepout_mask.png")
    kept = np.argwhere(mask == KEEP_OUT)
    centres = sub.geometry.cell_centers()[kept[:, 0], kept[:, 1]] if len(kept) \
        else np.zeros((0, 2))
    walked = ages(centres)
    return {"keepout_cells": len(kept), "keepout_threshold": KEEPOUT_THRESHOLD,
            "keepout_oldest_age_s": round(max(walked), 2) if walked else None,
            "keepout_free_cells": int(np.count_nonzero(mask == 0))}


class KeepoutTimeline:
    """nav2's keepout of the person during the run, sampled every ``period_s`` (wall): the
    kept-out cells and how far their centre is from where the person is at the map's clock
    (the simulated time of the latest ISM), so the summary shows the keepout follow the person
    while a robot sees it and fade once none does."""

    def __init__(self, client: Any, world: World, epoch: float, period_s: float = 1.0,
                 person: str = PERSON_LAYER) -> None:
        """``epoch``: Unix time just before the fleet starts (its stamps are ``epoch`` plus
        the simulated time, give or take the fleet's set-up).  ``person``: the person layer,
        or the pattern of every robot's."""
        self.client, self.world, self.epoch, self.period_s = client, world, epoch, period_s
        self.person = person
        self.rows: list[tuple[float, int, float | None]] = []  # (simulated s, cells, m)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="demo-keepout", daemon=True)

    def start(self) -> KeepoutTimeline:
        if warehouse_person(self.world) is not None:
            self._thread.start()
        return self

    def stop(self) -> list[tuple[float, int, float | None]]:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10.0)
        return self.rows

    def _run(self) -> None:
        from sogm_service.adapters.ros2.filters import KEEP_OUT, keepout_cells

        person = warehouse_person(self.world)
        g = self.world.geometry
        (w, h), (x, y) = g.size_m, g.centre()
        while not self._stop.wait(self.period_s) and person is not None:
            try:
                clock = self.client.stats().extra.get("map_time")
                if clock is None or not has_layer(self.client, self.person):
                    continue
                sub = self.client.submap(x=x, y=y, width=w, height=h, resolution=g.resolution,
                                         layers=[self.person], encoding="logodds_i16",
                                         interp="nearest")
            except Exception:  # a query refused or timed out: skip this sample
                continue
            t = float(clock) - self.epoch
            kept = np.argwhere(keepout_cells(np.asarray(sub.data[:1], np.int16),
                                             KEEPOUT_THRESHOLD) == KEEP_OUT)
            dist = None
            if len(kept):
                c = sub.geometry.cell_centers()[kept[:, 0], kept[:, 1]].mean(axis=0)
                # the person's nearest place in the last simulated second (the set-up blurs t)
                near = [person.position(max(0.0, t - k / 10)) for k in range(11)]
                dist = round(min(float(np.hypot(c[0] - px, c[1] - py)) for px, py in near), 2)
            self.rows.append((round(t, 1), len(kept), dist))


def report_moving(client: Any, world: World, out: Path, files: list[str],
                  duration_s: float, person_layer: str = PERSON_LAYER) -> dict[str, Any]:
    """``layer_person.png`` and what it shows: how old the spots still marked occupied are."""
    from sogm_service.apps.render import probability_image

    person = warehouse_person(world)
    if person is None or not has_layer(client, person_layer):
        return {}
    g = world.geometry
    w, h = g.size_m
    x, y = g.centre()
    sub = client.submap(x=x, y=y, yaw=0.0, width=w, height=h, resolution=g.resolution,
                        layers=[person_layer], encoding="prob_f32")
    p = sub.probabilities()[0]
    import cv2

    cv2.imwrite(str(out / "layer_person.png"), probability_image(p))
    files.append("layer_person.png")
    # When was the person last at each cell still marked occupied?
    radius = 0.3 + g.resolution
    times = np.arange(0.0, duration_s + 1e-9, 0.1)
    path = np.array([person.position(float(t)) for t in times])
    occ = np.argwhere(p > 0.6)
    centres = sub.geometry.cell_centers()[occ[:, 0], occ[:, 1]] if len(occ) else np.zeros((0, 2))

    def walked_ago(cells: np.ndarray) -> list[float]:
        """How long ago the person was last near each cell centre (never near: left out)."""
        out: list[float] = []
        for c in cells:
            near = np.hypot(path[:, 0] - c[0], path[:, 1] - c[1]) <= radius
            if near.any():
                out.append(duration_s - float(times[np.nonzero(near)[0][-1]]))
        return out
    ages = walked_ago(centres)
    old = OLD_HALF_LIVES * PERSON_HALF_LIFE_S
    now = person.position(duration_s)
    d_now = np.hypot(sub.geometry.cell_centers()[..., 0] - now[0],
                     sub.geometry.cell_centers()[..., 1] - now[1])
    return {
        "layer": person_layer, "half_life_s": PERSON_HALF_LIFE_S, "old_s": old,
        "occupied_cells": len(occ),
        "oldest_occupied_age_s": round(max(ages), 2) if ages else None,
        "occupied_older_than_old_s": sum(a > old for a in ages),
        "p_now": round(float(p[d_now <= 0.3].max()) if (d_now <= 0.3).any() else 0.5, 3),
        "person_now": [round(now[0], 2), round(now[1], 2)],
        "seen_cells": int(np.count_nonzero(np.abs(p - 0.5) > 1e-3)),
        "p_max_now": round(float(p.max()), 3),
        "max_age_possible_s": math.floor(duration_s),
        **keepout_report(client, world, out, files, walked_ago, person_layer),
    }
