"""Simulated worlds, robots and sensors that produce ISMs as a real fleet's would.

* :mod:`.worlds`: ground-truth worlds (class label + object height per cell), randomised by seed:
  a table-top room like the paper's Section IV scenarios and a fleet-scale warehouse.
* :mod:`.robots`: robots driving collision-free waypoint routes, optional odometry drift.
* :mod:`.sensors`: a tilted 2-D laser (``obstacle`` layer, via
:func:`sogm_service.adapters.laser.laser_ism`)
  and a camera with a semantic classifier (one ISM per class, coarser than the map).
* :mod:`.offline`: drive robots over a world and fuse their ISMs without Zenoh.
* :mod:`.fleet`: the same robots publishing over Zenoh (the only module here that imports zenoh).

Everything here is deterministic by seed.  The package namespace re-exports the pure parts
(not :mod:`.fleet`, so importing the simulator never pulls in Zenoh).
"""

from __future__ import annotations

from sogm_service.sim.offline import OfflineMap, map_scans, map_world
from sogm_service.sim.robots import SimStep, simulate
from sogm_service.sim.sensors import SemanticCamera, SensorIsm, TiltedLaser, default_sensors
from sogm_service.sim.worlds import World, tabletop_world, warehouse_world

__all__ = [
    "OfflineMap",
    "SemanticCamera",
    "SensorIsm",
    "SimStep",
    "TiltedLaser",
    "World",
    "default_sensors",
    "map_scans",
    "map_world",
    "simulate",
    "tabletop_world",
    "warehouse_world",
]
