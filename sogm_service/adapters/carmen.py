"""Reader of CARMEN log files (Radish data sets, e.g. the Intel Research Lab log).

Two kinds of front-laser lines are read, as CARMEN's own ``readlog.c`` reads them:

* old-style ``FLASER``::

      FLASER n r_1 .. r_n  x y theta  odom_x odom_y odom_theta  ipc_stamp ipc_host logger_stamp

  ``x y theta`` is the laser's pose (in the ``*-corrected`` logs after SLAM correction, in the
  map frame): that is :attr:`LaserScan.pose`.  The line carries no angles and no maximum
  range, so they are guessed as CARMEN does for a SICK (``carmen_laser_guess_fov`` and
  ``carmen_laser_guess_angle_increment``): 180/181 beams are 1 deg apart over 180 deg, 360/361
  beams 0.5 deg, 400/401 beams 0.25 deg over **100 deg**, any other count spreads 180 deg
  evenly; the maximum range is 80 m (readings at or beyond it are "no return", such as the
  81.83 m of the Intel log).  The first beam is at ``-fov / 2`` of the full field of view
  (-90 deg, or -50 deg for 400/401 beams) - as CARMEN's laser driver records a SICK
  (``config.start_angle = -0.5 * config.fov``).  (CARMEN's old-format reader writes -90 deg
  for every count, which would rotate a 100-deg scan by 40 deg against its own fov guess.)
  An ``n``-beam scan of an even count is the ``n + 1``-beam one without its last beam.
* ``ROBOTLASER1`` (CARMEN 0.7 ``carmen_robot_laser_message``)::

      ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy
                  remission_mode n r_1 .. r_n m rem_1 .. rem_m
                  laser_x laser_y laser_theta robot_x robot_y robot_theta
                  tv rv forward_safety_dist side_safety_dist turn_axis
                  timestamp host logger_timestamp

  The line carries its own angles (beam ``i`` at ``start_angle + i * angular_resolution``),
  maximum range and laser pose; the robot pose becomes :attr:`LaserScan.odom_pose`.

If a log holds both kinds (the same scans written twice by a converter), the kind seen first
is read and the other is skipped and counted (``duplicate laser``), so no scan is fused twice.
Every other line (comments, PARAM, ODOM, NEFF, rear lasers, ...) is skipped and counted by its
type (:class:`CarmenStats`); a malformed laser line (too few fields, a non-number, a non-finite
pose, inconsistent counts) is skipped and counted, never raised.
"""

from __future__ import annotations

import gzip
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from sogm_service.adapters.laser import laser_ism
from sogm_service.core.geometry import GridGeometry, Pose2D

log = logging.getLogger(__name__)

SICK_MAX_RANGE = 80.0
"""Maximum range CARMEN assumes for FLASER lines (m)."""

DEFAULT_USABLE_RANGE = 20.0
"""Ranges beyond this are trusted only as free space up to it (m): far SICK returns in an
office are sparse and their angular error spans several cells."""


@dataclass(frozen=True)
class LaserScan:
    """One planar scan: the laser's map-frame pose, ranges (m) and beam angles (rad)."""

    stamp: float
    pose: Pose2D
    ranges: npt.NDArray[np.float32]
    angles: npt.NDArray[np.float32]
    max_range: float
    odom_pose: Pose2D | None = None


LASER_TYPES: tuple[str, ...] = ("FLASER", "ROBOTLASER1")
"""The front-laser line types read (the first one seen in a log wins; module docstring)."""

_MAX_TYPE_NAMES = 64  # distinct line types counted by name; the rest are "other"


@dataclass
class CarmenStats:
    """What a :func:`read_carmen` pass saw (filled in as it goes).

    ``types`` counts every line by its type (the first word: ``FLASER``, ``ODOM``, ``PARAM``,
    ...; ``#`` comments as ``comment``, empty lines as ``blank``, anything that is not an
    upper-case word, or beyond the first 64 names, as ``other``); ``scans_by_type`` the laser
    lines that became scans; ``malformed_by_type`` the laser lines refused as malformed.
    ``skipped`` is every line that became no scan for another reason than being malformed
    (other types, a second laser kind), ``duplicate`` the lines of the second laser kind.
    """

    lines: int = 0
    scans: int = 0
    skipped: int = 0
    malformed: int = 0
    duplicate: int = 0
    laser_type: str | None = None
    types: dict[str, int] = field(default_factory=dict)
    scans_by_type: dict[str, int] = field(default_factory=dict)
    malformed_by_type: dict[str, int] = field(default_factory=dict)

    def count_type(self, kind: str) -> None:
        if kind not in self.types and len(self.types) >= _MAX_TYPE_NAMES:
            kind = "other"
        self.types[kind] = self.types.get(kind, 0) + 1

    def summary(self) -> str:
        """One line: every line type read, then what became scans and what was skipped."""
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.types.items(),
                                                          key=lambda kv: (-kv[1], kv[0])))
        used = ", ".join(f"{k} {n}" for k, n in sorted(self.scans_by_type.items())) or "none"
        bad = ", ".join(f"{k} {n}" for k, n in sorted(self.malformed_by_type.items()))
        return (f"lines: {self.lines} ({kinds or 'none'}); scans: {self.scans} ({used}); "
                f"skipped: {self.skipped} other lines, {self.duplicate} duplicate laser, "
                f"{self.malformed} malformed" + (f" ({bad})" if bad else ""))


def _line_type(line: str) -> str:
    words = line.split(maxsplit=1)
    if not words:
        return "blank"
    w = words[0]
    if w.startswith("#"):
        return "comment"
    if len(w) <= 32 and w.isascii() and w.replace("_", "").isalnum() and w[0].isalpha() \
            and w.upper() == w:
        return w
    return "other"


def carmen_guess_fov(n: int) -> float:
    """Field of view (rad) CARMEN guesses for an ``n``-beam SICK scan without a config.

    As ``carmen_laser_guess_fov``: 181 and 361 beams 180 deg, 180 beams 179 deg, 360 beams
    179.5 deg, 401 beams 100 deg, 400 beams 99.75 deg (even counts: the last beam is dropped),
    anything else 180 deg.  (CARMEN's source has ``M_PI / 100.0 * 99.75`` for 400 beams, a
    typo for ``/ 180.0`` that its own comment and angle increment contradict.)
    """
    if n in (180, 181, 360, 361, 400, 401):
        return carmen_guess_angle_increment(n) * (n - 1)
    return math.pi


def carmen_guess_angle_increment(n: int) -> float:
    """Angle between beams (rad), as ``carmen_laser_guess_angle_increment``."""
    if n in (180, 181):
        return math.pi / 180
    if n in (360, 361):
        return math.pi / 360
    if n in (400, 401):
        return math.pi / 720
    return math.pi / max(n - 1, 1)


def carmen_start_angle(n: int) -> float:
    """First beam's angle (rad): ``-fov / 2`` of the sensor's full field of view (module
    docstring) - -90 deg, or -50 deg for the 100-deg 400/401-beam setting."""
    return -math.radians(50.0) if n in (400, 401) else -math.pi / 2


def carmen_angles(n: int) -> npt.NDArray[np.float32]:
    """Beam angles of an ``n``-beam FLASER scan, as CARMEN guesses them for a SICK."""
    return (carmen_start_angle(n)
            + carmen_guess_angle_increment(n) * np.arange(n)).astype(np.float32)


def parse_flaser(line: str, max_range: float = SICK_MAX_RANGE) -> LaserScan:
    """Parse one FLASER line; ``ValueError`` if it is malformed."""
    words = line.split()
    if not words or words[0] != "FLASER":
        raise ValueError("not a FLASER line")
    n = int(words[1])
    if n <= 0 or len(words) < 2 + n + 7:
        raise ValueError(f"FLASER line with {len(words)} fields cannot hold {n} readings")
    ranges = np.array(words[2:2 + n], dtype=np.float32)
    x, y, th, ox, oy, oth, stamp = (float(w) for w in words[2 + n:2 + n + 7])
    if not all(math.isfinite(v) for v in (x, y, th, ox, oy, oth, stamp)):
        raise ValueError("non-finite pose or timestamp")
    return LaserScan(stamp, Pose2D(x, y, th), ranges, carmen_angles(n), max_range,
                     Pose2D(ox, oy, oth))


MAX_BEAMS = 1 << 16
"""More readings than this in one line is taken as a malformed line."""


def parse_robotlaser(line: str, max_range: float = SICK_MAX_RANGE) -> LaserScan:
    """Parse one ROBOTLASER1 line (module docstring); ``ValueError`` if it is malformed.

    The line's own ``maximum_range`` is the scan's; ``max_range`` is used only when the line's
    is not a positive number.
    """
    words = line.split()
    if not words or words[0] not in ("ROBOTLASER1", "ROBOTLASER2"):
        raise ValueError("not a ROBOTLASER line")
    if len(words) < 9:
        raise ValueError(f"ROBOTLASER line with only {len(words)} fields")
    start, fov, res, line_max = (float(w) for w in words[2:6])
    n = int(words[8])
    if not 0 < n <= MAX_BEAMS:
        raise ValueError(f"ROBOTLASER line with {n} readings")
    at = 9 + n
    if len(words) <= at:
        raise ValueError(f"ROBOTLASER line with {len(words)} fields cannot hold {n} readings")
    m = int(words[at])
    if not 0 <= m <= MAX_BEAMS:
        raise ValueError(f"ROBOTLASER line with {m} remission values")
    tail = at + 1 + m
    if len(words) < tail + 12:
        raise ValueError(f"ROBOTLASER line with {len(words)} fields cannot hold {n} readings "
                         f"and {m} remissions")
    ranges = np.array(words[9:9 + n], dtype=np.float32)
    x, y, th, rx, ry, rth = (float(w) for w in words[tail:tail + 6])
    stamp = float(words[tail + 11])
    if not all(math.isfinite(v) for v in (start, fov, res, x, y, th, rx, ry, rth, stamp)):
        raise ValueError("non-finite angle, pose or timestamp")
    if res == 0.0 or abs(res) * (n - 1) > 2 * math.pi + 1e-6:
        raise ValueError(f"angular resolution {res} does not fit {n} readings in one turn")
    usable = line_max if math.isfinite(line_max) and line_max > 0 else max_range
    angles = (start + res * np.arange(n)).astype(np.float32)
    return LaserScan(stamp, Pose2D(x, y, th), ranges, angles, usable, Pose2D(rx, ry, rth))


_PARSERS = {"FLASER": parse_flaser, "ROBOTLASER1": parse_robotlaser}


def _open_text(path: str | Path) -> Iterator[str]:
    p = Path(path)
    with p.open("rb") as raw:
        gz = raw.read(2) == b"\x1f\x8b"  # by content, not by name
    opener = gzip.open if gz else open
    with opener(p, "rt", encoding="ascii", errors="replace") as f:
        yield from f


def read_carmen(path: str | Path, *, limit: int | None = None,
                max_range: float = SICK_MAX_RANGE,
                stats: CarmenStats | None = None) -> Iterator[LaserScan]:
    """Yield the front-laser scans (FLASER or ROBOTLASER1) of a CARMEN log, at most ``limit``.

    ``max_range`` is FLASER's (the line has none).  Other lines are skipped; malformed laser
    lines are skipped, counted in ``stats`` and logged at debug level.  Pass a
    :class:`CarmenStats` to see the counts (by line type: :meth:`CarmenStats.summary`).
    With ``limit`` the file is read only up to the last scan yielded.
    """
    st = stats if stats is not None else CarmenStats()
    if limit is not None and limit <= 0:
        return
    for line in _open_text(path):
        st.lines += 1
        kind = _line_type(line)
        st.count_type(kind)
        parser = _PARSERS.get(kind)
        if parser is None:
            st.skipped += 1
            continue
        if st.laser_type is not None and kind != st.laser_type:
            st.skipped += 1
            st.duplicate += 1
            continue
        try:
            scan = parser(line, max_range)
        except (ValueError, IndexError) as exc:
            st.malformed += 1
            st.malformed_by_type[kind] = st.malformed_by_type.get(kind, 0) + 1
            log.debug("line %d: malformed %s line skipped: %s", st.lines, kind, exc)
            continue
        st.laser_type = kind
        st.scans += 1
        st.scans_by_type[kind] = st.scans_by_type.get(kind, 0) + 1
        yield scan
        if limit is not None and st.scans >= limit:
            return


def scan_ism(scan: LaserScan, resolution: float = 0.05,
             usable_range: float = DEFAULT_USABLE_RANGE, *, p_free: float = 0.3,
             p_occ: float = 0.8,
             hit_width_cells: int = 1) -> tuple[GridGeometry, npt.NDArray[np.float32]]:
    """The ``obstacle`` ISM of one recorded scan (:func:`sogm_service.adapters.laser.laser_ism`).

    The device's no-return readings (``>= scan.max_range``) are dropped; readings beyond
    ``usable_range`` are free up to it.  Sensor-aligned grid at ``scan.pose``.
    """
    return laser_ism(scan.ranges, scan.angles, scan.pose, resolution,
                     min(usable_range, scan.max_range), p_free=p_free, p_occ=p_occ,
                     hit_width_cells=hit_width_cells, device_max_range=scan.max_range)
