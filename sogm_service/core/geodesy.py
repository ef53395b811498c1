"""Geo-referencing of the map frame: map metres <-> WGS-84 latitude/longitude/altitude.

Pure (no I/O).  The map is geo-referenced by one *datum*: the WGS-84 position of the map
frame's origin, with the map frame **ENU-aligned** (x east, y north, z up), as REP-105 asks of
a ``map`` frame.  The paper publishes a NavSat datum with every tile (section III-E); a tile's
datum here is the geodetic position of the tile's origin corner.

Conversion: **exact**, through the maintained `pymap3d <https://github.com/geospace-code/pymap3d>`_
(pure Python): the map point ``(x, y, z)`` is a vector in the local East-North-Up frame of the
datum, rotated into Earth-centred Earth-fixed (ECEF) coordinates and converted to geodetic
WGS-84 latitude, longitude and ellipsoidal height (``pymap3d.enu2geodetic``; the inverse is
``pymap3d.geodetic2enu``).  The map plane is the tangent plane at the datum, so a point on
the floor (``z = 0``) far from the datum lies *above* the ellipsoid (``d^2 / 2R``: 0.8 m at
3.2 km) - that is where the plane really is, and it is what a GNSS receiver on that plane
would report.  Tested against an independent ENU -> ECEF -> geodetic conversion within 1 mm
up to 200 km from the datum at latitudes 0, 45, 70 and -33 deg
(``tests/unit/core/test_geodesy.py``).

First-order scale factors with a constant altitude would drift by 11 m at 10 km (9 m
horizontally) at 45 deg latitude: the conversion is exact instead.

Datums closer than 0.1 deg to a pole are refused: there the datum's east axis (which follows
the datum longitude) turns by tens of degrees per metre of latitude - the map frame would be
ill-defined rather than wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Protocol

import pymap3d

WGS84_A: Final = 6378137.0
"""Semi-major axis (m)."""

WGS84_F: Final = 1.0 / 298.257223563
"""Flattening."""

WGS84_E2: Final = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""

_MAX_ABS_LAT: Final = 89.9
"""Datums beyond this latitude are refused (module docstring)."""

_WGS84: Final = pymap3d.Ellipsoid.from_name("wgs84")


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


def _wrap_lon(lon: float) -> float:
    """Longitude into [-180, 180)."""
    return (lon + 180.0) % 360.0 - 180.0


class LocalTangentPlane:
    """The ENU-aligned map frame around a datum: exact WGS-84 conversions (module docstring)."""

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

    def to_geodetic(self, x: float, y: float, z: float = 0.0) -> GeoPoint:
        """Map-frame metres (x east, y north, z up) -> WGS-84 (exact)."""
        d = self.datum
        if x == 0.0 and y == 0.0 and z == 0.0:
            return d  # the datum itself, bit for bit (no round trip through ECEF)
        lat, lon, alt = pymap3d.enu2geodetic(float(x), float(y), float(z), d.latitude,
                                             d.longitude, d.altitude, ell=_WGS84, deg=True)
        return GeoPoint(float(lat), _wrap_lon(float(lon)), float(alt))

    def to_map(self, point: GeodeticLike) -> tuple[float, float, float]:
        """WGS-84 -> map-frame metres ``(x, y, z)``; the inverse of :meth:`to_geodetic`."""
        d = self.datum
        e, n, u = pymap3d.geodetic2enu(float(point.latitude), float(point.longitude),
                                       float(point.altitude), d.latitude, d.longitude,
                                       d.altitude, ell=_WGS84, deg=True)
        return float(e), float(n), float(u)
