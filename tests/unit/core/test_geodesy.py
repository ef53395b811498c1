"""Exact georeferencing: the map frame's ENU <-> WGS-84 against an independent reference.

The reference is written here from first principles (no pymap3d): geodetic -> ECEF in closed
form, ENU -> ECEF by the rotation matrix of the datum, and ECEF -> geodetic by the iterative
latitude formula (iterated to machine precision).  Errors are measured in metres: both results
are taken back to ECEF with the closed form and compared by Euclidean distance.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from sogm_service.core.geodesy import GeoPoint, LocalTangentPlane
from sogm_service.wire.messages import GeodeticFix

A = 6378137.0  # WGS-84 semi-major axis
F = 1.0 / 298.257223563  # WGS-84 flattening
E2 = F * (2.0 - F)


def geodetic_to_ecef(lat: float, lon: float, h: float) -> npt.NDArray[np.float64]:
    phi, lam = math.radians(lat), math.radians(lon)
    n = A / math.sqrt(1.0 - E2 * math.sin(phi) ** 2)
    return np.array([(n + h) * math.cos(phi) * math.cos(lam),
                     (n + h) * math.cos(phi) * math.sin(lam),
                     (n * (1.0 - E2) + h) * math.sin(phi)])


def enu_rotation(lat: float, lon: float) -> npt.NDArray[np.float64]:
    """Columns: the east, north and up unit vectors of the datum in ECEF."""
    phi, lam = math.radians(lat), math.radians(lon)
    sp, cp, sl, cl = math.sin(phi), math.cos(phi), math.sin(lam), math.cos(lam)
    return np.array([[-sl, -sp * cl, cp * cl],
                     [cl, -sp * sl, cp * sl],
                     [0.0, cp, sp]])


def ecef_to_geodetic(p: npt.NDArray[np.float64]) -> tuple[float, float, float]:
    """Iterative: phi = atan2(z + e2 N sin(phi), p), to convergence (far from the poles)."""
    x, y, z = (float(v) for v in p)
    r = math.hypot(x, y)
    lon = math.atan2(y, x)
    phi = math.atan2(z, r * (1.0 - E2))
    for _ in range(50):
        n = A / math.sqrt(1.0 - E2 * math.sin(phi) ** 2)
        nxt = math.atan2(z + E2 * n * math.sin(phi), r)
        if abs(nxt - phi) < 1e-15:
            phi = nxt
            break
        phi = nxt
    n = A / math.sqrt(1.0 - E2 * math.sin(phi) ** 2)
    h = r / math.cos(phi) - n
    return math.degrees(phi), math.degrees(lon), h


def reference_to_geodetic(datum: GeoPoint, enu: tuple[float, float, float]
                          ) -> tuple[float, float, float]:
    ecef = geodetic_to_ecef(datum.latitude, datum.longitude, datum.altitude) + \
        enu_rotation(datum.latitude, datum.longitude) @ np.array(enu)
    return ecef_to_geodetic(ecef)


def distance_m(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    return float(np.linalg.norm(geodetic_to_ecef(*a) - geodetic_to_ecef(*b)))


DATUMS = [GeoPoint(0.0, 0.0, 0.0), GeoPoint(45.0, 7.0, 250.0), GeoPoint(70.0, 25.0, 30.0),
          GeoPoint(-33.0, 151.0, 60.0), GeoPoint(45.0, 179.9, 0.0)]


def _points() -> list[tuple[float, float, float]]:
    """Points up to 200 km from the datum in all directions, on and off the map plane."""
    rng = np.random.default_rng(19)
    pts: list[tuple[float, float, float]] = [(10_000.0, 0.0, 0.0), (0.0, 200_000.0, 0.0),
                                             (-141_000.0, -141_000.0, 5.0), (12.8, 0.0, 0.0)]
    for d in (1.0, 300.0, 1_000.0, 10_000.0, 50_000.0, 200_000.0):
        for bearing in rng.uniform(0.0, 2.0 * math.pi, 4):
            z = float(rng.uniform(-50.0, 500.0))
            pts.append((d * math.sin(bearing), d * math.cos(bearing), z))
    return pts


@pytest.mark.parametrize("datum", DATUMS, ids=lambda d: f"lat{d.latitude:g}_lon{d.longitude:g}")
def test_to_geodetic_is_exact_within_a_centimetre_up_to_200_km(datum: GeoPoint) -> None:
    plane = LocalTangentPlane(datum)
    worst = 0.0
    for enu in _points():
        got = plane.to_geodetic(*enu)
        ref = reference_to_geodetic(datum, enu)
        assert -180.0 <= got.longitude < 180.0
        err = distance_m((got.latitude, got.longitude, got.altitude), ref)
        worst = max(worst, err)
        # The point is where the ENU vector says, not just consistent with the reference.
        assert err < 0.01, (enu, got, ref)
    assert worst < 0.001  # in fact sub-millimetre


@pytest.mark.parametrize("datum", DATUMS, ids=lambda d: f"lat{d.latitude:g}_lon{d.longitude:g}")
def test_to_map_is_the_exact_inverse(datum: GeoPoint) -> None:
    plane = LocalTangentPlane(datum)
    rot = enu_rotation(datum.latitude, datum.longitude)
    origin = geodetic_to_ecef(datum.latitude, datum.longitude, datum.altitude)
    for enu in _points():
        lat, lon, h = reference_to_geodetic(datum, enu)
        x, y, z = plane.to_map(GeoPoint(lat, lon, h))
        assert np.linalg.norm(np.array([x, y, z]) - np.array(enu)) < 0.01
        # and independently: ECEF difference rotated back into ENU
        back = rot.T @ (geodetic_to_ecef(lat, lon, h) - origin)
        assert np.allclose(back, [x, y, z], atol=0.01)


def test_literal_values_at_the_equator() -> None:
    """Closed-form cases needing no iteration: on the equator the east axis is ECEF +y."""
    plane = LocalTangentPlane(GeoPoint(0.0, 0.0, 0.0))
    p = plane.to_geodetic(100_000.0, 0.0, 0.0)  # ECEF (a, 100 km, 0)
    assert p.latitude == pytest.approx(0.0, abs=1e-12)
    assert p.longitude == pytest.approx(math.degrees(math.atan2(100_000.0, A)), abs=1e-12)
    assert p.altitude == pytest.approx(math.hypot(A, 100_000.0) - A, abs=1e-6)  # 783.88 m
    assert p.altitude == pytest.approx(783.880, abs=0.001)
    up = plane.to_geodetic(0.0, 0.0, 1234.5)
    assert (up.latitude, up.longitude) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert up.altitude == pytest.approx(1234.5, abs=1e-6)


def test_the_first_order_plane_would_have_been_metres_off() -> None:
    """What the issue measured: at 45 deg, 10 km east, the old first-order formula was ~11 m
    off; the exact conversion agrees with the reference to well under a millimetre."""
    datum = GeoPoint(45.0, 7.0, 0.0)
    plane = LocalTangentPlane(datum)
    ref = reference_to_geodetic(datum, (10_000.0, 0.0, 0.0))
    m = 6367381.816  # WGS-84 meridian radius at 45 deg
    n = 6388838.290  # prime-vertical radius at 45 deg
    first_order = (45.0, 7.0 + math.degrees(10_000.0 / (n * math.cos(math.radians(45.0)))), 0.0)
    assert m > 0 and distance_m(first_order, ref) > 5.0
    got = plane.to_geodetic(10_000.0, 0.0)
    assert distance_m((got.latitude, got.longitude, got.altitude), ref) < 1e-3


def test_datum_is_returned_as_is_and_wire_fixes_are_accepted() -> None:
    fix = GeodeticFix(latitude=-33.0, longitude=151.0, altitude=60.0)
    plane = LocalTangentPlane(fix)
    assert plane.to_geodetic(0.0, 0.0) == GeoPoint(-33.0, 151.0, 60.0)
    assert plane.to_map(fix) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    for bad in (GeoPoint(89.95, 0.0), GeoPoint(math.nan, 0.0), GeoPoint(0.0, 181.0),
                GeoPoint(0.0, 0.0, math.inf)):
        with pytest.raises(ValueError):
            LocalTangentPlane(bad)
