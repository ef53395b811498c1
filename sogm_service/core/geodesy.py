"""Geo-referencing of the map frame: map metres <-> WGS-84 latitude/longitude/altitude.

Pure (no I/O).  The map is geo-referenced by one *datum*: the WGS-84 position of the map
frame's origin, with the map frame **ENU-aligned** (x east, y north, z up), as REP-105 asks of
a ``map`` frame.  The paper publishes a NavSat datum with every tile (section III-E); a tile's
datum here is the geodetic position of the tile's origin corner.

Conversion: a local tangent plane at the datum with the WGS-84 radii of curvature of that
latitude (meridian radius ``M`` for north, prime-vertical radius ``N`` for east)::

    lat = lat0 + y / M(lat0)              lon = lon0 + x / (N(lat0) * cos(lat0))
    alt = alt0 (+ z)

Why this one: it is exact to first order, cheap, invertible in closed form, and its error is
far below a grid cell over a fleet's working area: the horizontal error grows like
``d^2 / R`` (about 1 cm at 300 m, 16 cm at 1 km from the datum) and the plane does not follow
the Earth's curvature in altitude (``d^2 / 2R``: 7 mm at 300 m).  Maps spanning tens of
kilometres should be split into several maps, each with its own datum.  It is not defined at
the poles (``cos(lat0) = 0``), which the datum check rejects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Protocol

WGS84_A: Final = 6378137.0
"""Semi-major axis (m)."""

WGS84_F: Final = 1.0 / 298.257223563
"""Flattening."""

WGS84_E2: Final = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""

_MAX_ABS_LAT: Final = 89.9
"""The tangent-plane longitude scale blows up near the poles: refuse datums beyond this."""


class GeodeticLike(Protocol):
    """Anything with WGS-84 ``latitude``/``longitude`` (deg) and ``altitude`` (m) attributes,
    e.g. :class:`GeoPoint` or the wire model ``messages.GeodeticFix``."""

    @property
    def latitude(self) -> float: ...

    @property
    def longitude(self) -> float: ...

    @property
    def altitude(self) -> float: ...


@dataclass(frozen=True, slots=True)
class GeoPoint:
    """A WGS-84 position: latitude and longitude in degrees, altitude in metres."""

    latitude: float
    longitude: float
    altitude: float = 0.0

    @staticmethod
    def of(fix: GeodeticLike) -> GeoPoint:
        """Copy any geodetic-like object (e.g. a pydantic ``GeodeticFix``) into a GeoPoint."""
        return GeoPoint(float(fix.latitude), float(fix.longitude), float(fix.altitude))

    def as_dict(self) -> dict[str, float]:
        return {"latitude": self.latitude, "longitude": self.longitude,
                "altitude": self.altitude}


def radii_of_curvature(latitude_deg: float) -> tuple[float, float]:
    """WGS-84 ``(M, N)`` in metres at a latitude: meridian and prime-vertical radii."""
    s = math.sin(math.radians(latitude_deg))
    w2 = 1.0 - WGS84_E2 * s * s
    n = WGS84_A / math.sqrt(w2)
    m = WGS84_A * (1.0 - WGS84_E2) / (w2 * math.sqrt(w2))
    return m, n


class LocalTangentPlane:
    """The ENU-aligned map frame around a datum (module docstring: the formula and its error)."""

    def __init__(self, datum: GeodeticLike) -> None:
        self.datum = GeoPoint.of(datum)
        lat = self.datum.latitude
        if not (math.isfinite(lat) and abs(lat) <= _MAX_ABS_LAT):
            raise ValueError(f"datum latitude must lie within ±{_MAX_ABS_LAT} deg, got {lat}")
        if not (math.isfinite(self.datum.longitude) and abs(self.datum.longitude) <= 180.0):
            raise ValueError(f"datum longitude must lie within ±180 deg, "
                             f"got {self.datum.longitude}")
        if not math.isfinite(self.datum.altitude):
            raise ValueError("datum altitude must be finite")
        m, n = radii_of_curvature(lat)
        # Degrees per metre north and east at the datum.
        self._deg_per_m_north = math.degrees(1.0 / m)
        self._deg_per_m_east = math.degrees(1.0 / (n * math.cos(math.radians(lat))))

    def to_geodetic(self, x: float, y: float, z: float = 0.0) -> GeoPoint:
        """Map-frame metres (x east, y north, z up) -> WGS-84."""
        lon = self.datum.longitude + x * self._deg_per_m_east
        lon = (lon + 180.0) % 360.0 - 180.0  # stay in [-180, 180) across the antimeridian
        return GeoPoint(self.datum.latitude + y * self._deg_per_m_north, lon,
                        self.datum.altitude + z)

    def to_map(self, point: GeodeticLike) -> tuple[float, float, float]:
        """WGS-84 -> map-frame metres ``(x, y, z)``; the inverse of :meth:`to_geodetic`."""
        dlon = (float(point.longitude) - self.datum.longitude + 180.0) % 360.0 - 180.0
        x = dlon / self._deg_per_m_east
        y = (float(point.latitude) - self.datum.latitude) / self._deg_per_m_north
        return x, y, float(point.altitude) - self.datum.altitude
