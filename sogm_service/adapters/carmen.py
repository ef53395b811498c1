"""Reader of CARMEN log files (Radish data sets, e.g. the Intel Research Lab log).

Only old-style front-laser lines are read::

    FLASER n r_1 .. r_n  x y theta  odom_x odom_y odom_theta  ipc_stamp ipc_host logger_stamp

In the ``*-corrected`` logs ``x y theta`` is the laser's pose after SLAM correction, in the map
frame: that is :attr:`LaserScan.pose`.  The line carries no angles and no maximum range, so they
are guessed as CARMEN's own log reader does for a SICK: the scan starts at -90 deg; 180 or 181
beams are 1 deg apart, 360/361 beams 0.5 deg, 400/401 beams 0.25 deg, any other count spreads
180 deg evenly; the maximum range is 80 m (readings at or beyond it are "no return", such as
the 81.83 m of the Intel log).

Every other line (comments, PARAM, ODOM, NEFF, ...) is skipped and counted; a malformed FLASER
line (too few fields, a non-number, a non-finite pose) is skipped and counted, never raised.
"""

from __future__ import annotations

import gzip
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
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


@dataclass
class CarmenStats:
    """What a :func:`read_carmen` pass saw (filled in as it goes)."""

    lines: int = 0
    scans: int = 0
    skipped: int = 0
    malformed: int = 0


def carmen_angles(n: int) -> npt.NDArray[np.float32]:
    """Beam angles of an ``n``-beam FLASER scan, as CARMEN guesses them for a SICK."""
    if n in (180, 181):
        inc = math.pi / 180
    elif n in (360, 361):
        inc = math.pi / 360
    elif n in (400, 401):
        inc = math.pi / 720
    else:
        inc = math.pi / max(n - 1, 1)
    return (-math.pi / 2 + inc * np.arange(n)).astype(np.float32)


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
    """Yield the FLASER scans of a CARMEN log (gzip or plain text), at most ``limit``.

    Non-FLASER lines are skipped; malformed FLASER lines are skipped, counted in ``stats`` and
    logged once each at debug level.  Pass a :class:`CarmenStats` to see the counts.
    """
    st = stats if stats is not None else CarmenStats()
    if limit is not None and limit <= 0:
        return
    for line in _open_text(path):
        st.lines += 1
        if not line.lstrip().startswith("FLASER"):
            st.skipped += 1
            continue
        try:
            scan = parse_flaser(line, max_range)
        except (ValueError, IndexError) as exc:
            st.malformed += 1
            log.debug("line %d: malformed FLASER line skipped: %s", st.lines, exc)
            continue
        st.scans += 1
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
