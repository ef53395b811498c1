"""The demo's sensors: the laser cast on the map's lattice (sharp walls) and a
moving person in a layer that forgets (:mod:`sogm_service.sim.moving`).

The person layer is reported on its own (``layer_person.png`` and ``summary.json``'s
``moving``); every other output is computed over the other layers.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sogm_service.sim.moving import PersonDetector, warehouse_person
from sogm_service.sim.robots import SimStep
from sogm_service.sim.sensors import Sensor, SensorIsm, TiltedLaser, default_sensors
from sogm_service.sim.worlds import World

PERSON_LAYER = "person"
PERSON_HALF_LIFE_S = 5.0
"""Half-life of the person layer, in seconds of the ISM stamps (simulated time)."""
MOVING_LAYERS = (PERSON_LAYER,)
OLD_HALF_LIVES = 4.0
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


def forgetting_config(config: Any, world: World) -> Any:
    """The demo's server config with the person layer forgetting."""
    if warehouse_person(world) is None:
        return config
    return config.model_copy(update={"map": config.map.model_copy(
        update={"forget": {PERSON_LAYER: PERSON_HALF_LIFE_S}})})


def report_moving(client: Any, world: World, out: Path, files: list[str],
                  duration_s: float) -> dict[str, Any]:
    """``layer_person.png`` and what it shows: how old the spots still marked occupied are."""
    from sogm_service.apps.render import probability_image

    person = warehouse_person(world)
    if person is None or PERSON_LAYER not in client.info().layers:
        return {}
    g = world.geometry
    w, h = g.size_m
    x, y = g.centre()
    sub = client.submap(x=x, y=y, yaw=0.0, width=w, height=h, resolution=g.resolution,
                        layers=[PERSON_LAYER], encoding="prob_f32")
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
    ages = []
    for c in centres:
        near = np.hypot(path[:, 0] - c[0], path[:, 1] - c[1]) <= radius
        if near.any():
            ages.append(duration_s - float(times[np.nonzero(near)[0][-1]]))
    old = OLD_HALF_LIVES * PERSON_HALF_LIFE_S
    now = person.position(duration_s)
    d_now = np.hypot(sub.geometry.cell_centers()[..., 0] - now[0],
                     sub.geometry.cell_centers()[..., 1] - now[1])
    return {
        "layer": PERSON_LAYER, "half_life_s": PERSON_HALF_LIFE_S, "old_s": old,
        "occupied_cells": len(occ),
        "oldest_occupied_age_s": round(max(ages), 2) if ages else None,
        "occupied_older_than_old_s": sum(a > old for a in ages),
        "p_now": round(float(p[d_now <= 0.3].max()) if (d_now <= 0.3).any() else 0.5, 3),
        "person_now": [round(now[0], 2), round(now[1], 2)],
        "seen_cells": int(np.count_nonzero(np.abs(p - 0.5) > 1e-3)),
        "p_max_now": round(float(p.max()), 3),
        "max_age_possible_s": math.floor(duration_s),
    }
