"""Simulated robots: collision-free waypoint routes, odometry drift, and the fleet iterator.

A robot turns in place toward its next waypoint, then drives straight to it at constant speed.
Waypoints are drawn at random from the world's drivable cells (clear of obstacles by the robot's
radius) and accepted only when the straight segment to them stays drivable, so routes never
cross an object.  All randomness comes from ``numpy.random.default_rng`` seeded with
``(seed, robot index, ...)``: the same seed gives the same fleet, whatever the iteration order.

Odometry noise: the robot integrates its own motion increments with Gaussian errors
proportional to the distance and angle moved (``odom_noise`` = relative sigma), starting from its
true start pose: its *reported* pose drifts as a real robot's odometry does.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import Pose2D
from sogm_service.sim.sensors import Sensor, SensorIsm, default_sensors
from sogm_service.sim.worlds import World


@dataclass(frozen=True)
class Route:
    """Knots ``(time, x, y, yaw)`` of a piecewise-linear trajectory; linear in between."""

    times: npt.NDArray[np.float64]
    poses: npt.NDArray[np.float64]  # (K, 3) x, y, unwrapped yaw

    def pose_at(self, t: float) -> Pose2D:
        """Pose at time ``t`` (held at the last knot after the end)."""
        x = float(np.interp(t, self.times, self.poses[:, 0]))
        y = float(np.interp(t, self.times, self.poses[:, 1]))
        yaw = float(np.interp(t, self.times, self.poses[:, 2]))
        return Pose2D(x, y, math.remainder(yaw, 2 * math.pi))

    @property
    def duration(self) -> float:
        return float(self.times[-1])


def _segment_clear(drivable: npt.NDArray[np.bool_], world: World, a: npt.NDArray[np.float64],
                   b: npt.NDArray[np.float64]) -> bool:
    """Whether every point of segment a-b lies on a drivable cell."""
    n = int(np.ceil(np.linalg.norm(b - a) / world.geometry.resolution)) + 2
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    uv = world.geometry.world_to_index(pts)
    u, v = uv[:, 0], uv[:, 1]
    if (u < 0).any() or (v < 0).any() or (u >= world.geometry.width).any() or \
            (v >= world.geometry.height).any():
        return False
    return bool(drivable[v, u].all())


def _random_cells(rng: np.random.Generator, world: World, drivable: npt.NDArray[np.bool_],
                  n: int) -> npt.NDArray[np.float64]:
    """``n`` random map-frame points on drivable cells (cell centres)."""
    vs, us = np.nonzero(drivable)
    if len(us) == 0:
        raise ValueError("the world has no drivable cell for this robot size")
    pick = rng.integers(0, len(us), size=n)
    m = world.geometry.cell_to_world()
    return np.stack([m[0, 0] * us[pick] + m[0, 2], m[1, 1] * vs[pick] + m[1, 2]], axis=1)


def _start_in_band(rng: np.random.Generator, world: World, drivable: npt.NDArray[np.bool_],
                   i: int, n: int) -> npt.NDArray[np.float64] | None:
    """A drivable start in the ``i``-th of ``n`` horizontal bands of the world, so that a fleet
    spreads over the site instead of starting in one corner (None: that band has no room)."""
    h = drivable.shape[0]
    band = np.zeros_like(drivable)
    band[i * h // n:(i + 1) * h // n] = True
    if not (drivable & band).any():
        return None
    return _random_cells(rng, world, drivable & band, 1)[0]


def plan_route(world: World, rng: np.random.Generator, duration_s: float, speed: float,
               turn_rate: float, hop: tuple[float, float],
               start: npt.NDArray[np.float64] | None = None) -> Route:
    """Random collision-free waypoint route lasting at least ``duration_s``.

    ``hop`` bounds the straight-line distance (m) to the next waypoint.
    """
    drivable = world.drivable()
    pos = _random_cells(rng, world, drivable, 1)[0] if start is None else start
    yaw = float(rng.uniform(-math.pi, math.pi))
    knots = [(0.0, pos[0], pos[1], yaw)]
    visited = [pos]
    t = 0.0
    while t < duration_s:
        goal = _next_waypoint(rng, world, drivable, pos, hop, visited)
        if goal is None:  # boxed in: turn on the spot and try again
            yaw += math.pi / 2
            t += (math.pi / 2) / turn_rate
            knots.append((t, pos[0], pos[1], yaw))
            continue
        d = goal - pos
        heading = yaw + math.remainder(math.atan2(d[1], d[0]) - yaw, 2 * math.pi)
        t += abs(heading - yaw) / turn_rate
        knots.append((t, pos[0], pos[1], heading))
        t += float(np.linalg.norm(d)) / speed
        knots.append((t, goal[0], goal[1], heading))
        pos, yaw = goal, heading
        visited.append(pos)
    arr = np.array(knots, dtype=np.float64)
    return Route(arr[:, 0], arr[:, 1:])


def _next_waypoint(rng: np.random.Generator, world: World, drivable: npt.NDArray[np.bool_],
                   pos: npt.NDArray[np.float64], hop: tuple[float, float],
                   visited: Sequence[npt.NDArray[np.float64]]) -> npt.NDArray[np.float64] | None:
    """A random drivable point ``hop[0]..hop[1]`` m away in plain sight, or None.

    Of a handful of reachable candidates the one farthest from the recent waypoints wins, so
    robots explore instead of pacing one corner (better coverage per simulated second).
    """
    cands = _random_cells(rng, world, drivable, 64)
    dist = np.linalg.norm(cands - pos, axis=1)
    reachable = [c for c in cands[(dist >= hop[0]) & (dist <= hop[1])][:16]
                 if _segment_clear(drivable, world, pos, c)]
    if not reachable:
        return None
    recent = np.asarray(visited[-6:])
    novelty = [float(np.min(np.linalg.norm(recent - c, axis=1))) for c in reachable]
    return np.asarray(reachable[int(np.argmax(novelty))], dtype=np.float64)


@dataclass
class Robot:
    """A robot: its route, its sensors and its odometry error model."""

    name: str
    route: Route
    sensors: Sequence[Sensor]
    odom_noise: float = 0.0
    _rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    _last_true: Pose2D | None = None
    _reported: Pose2D | None = None

    def reported_pose(self, true_pose: Pose2D) -> Pose2D:
        """Advance dead reckoning to ``true_pose`` (call once per step, in time order)."""
        if self._reported is None or self._last_true is None or self.odom_noise <= 0:
            self._reported = true_pose
        else:
            d = self._last_true.inverse().compose(true_pose)
            dist, turn = math.hypot(d.x, d.y), abs(d.yaw)
            n = self._rng.normal(0.0, self.odom_noise, size=3)
            noisy = Pose2D(d.x + n[0] * dist, d.y + n[1] * dist,
                           d.yaw + n[2] * (turn + 0.2 * dist))
            self._reported = self._reported.compose(noisy)
        self._last_true = true_pose
        return self._reported


@dataclass(frozen=True)
class SimStep:
    """One robot at one time step: its true and reported pose and its sensors' ISMs."""

    robot: str
    stamp: float
    step: int
    true_pose: Pose2D
    pose: Pose2D
    isms: list[SensorIsm]


def motion_profile(world: World) -> tuple[float, float, tuple[float, float]]:
    """``(speed m/s, turn rate rad/s, waypoint hop m)`` suited to the world's scale."""
    if world.kind == "tabletop":
        return 0.15, 1.0, (0.4, 2.0)
    return 1.0, 0.8, (3.0, 25.0)


def make_robots(world: World, robots: int, duration_s: float, seed: int, *,
                odom_noise: float = 0.0,
                sensors: Sequence[Sensor] | None = None) -> list[Robot]:
    """``robots`` robots named ``robot1..N`` with routes lasting ``duration_s``."""
    speed, turn, hop = motion_profile(world)
    suite: Sequence[Sensor] = default_sensors(world) if sensors is None else sensors
    drivable = world.drivable()
    fleet = []
    for i in range(robots):
        rng = np.random.default_rng([seed, i, 1])
        start = _start_in_band(rng, world, drivable, i, robots)
        route = plan_route(world, rng, duration_s, speed, turn, hop, start=start)
        fleet.append(Robot(f"robot{i + 1}", route, suite, odom_noise,
                           np.random.default_rng([seed, i, 2])))
    return fleet


def simulate(world: World, robots: int = 3, duration_s: float = 20.0, rate_hz: float = 4.0,
             seed: int = 0, *, odom_noise: float = 0.0,
             sensors: Sequence[Sensor] | None = None) -> Iterator[SimStep]:
    """Drive ``robots`` robots over ``world``; per step and robot yield a :class:`SimStep`.

    Steps are at ``k / rate_hz`` for ``k = 0 .. floor(duration_s * rate_hz)``, robots in name
    order within a step.  Sensor noise of step ``k``, robot ``i``, sensor ``j`` is seeded by
    ``(seed, i, k, j)``.
    """
    fleet = make_robots(world, robots, duration_s, seed, odom_noise=odom_noise, sensors=sensors)
    for k in range(math.floor(duration_s * rate_hz) + 1):
        t = k / rate_hz
        for i, robot in enumerate(fleet):
            true_pose = robot.route.pose_at(t)
            pose = robot.reported_pose(true_pose)
            isms: list[SensorIsm] = []
            for j, sensor in enumerate(robot.sensors):
                rng = np.random.default_rng([seed, i, k, j, 3])
                isms.extend(sensor.isms(world, true_pose, pose, rng))
            yield SimStep(robot.name, t, k, true_pose, pose, isms)
