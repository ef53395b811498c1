"""The viewer's hub (apps/viewer/hub): what it tells the page about the map."""

from __future__ import annotations

import pytest

from tests.unit.apps.viewer.test_tiles import RES


def test_cursor_latitude_longitude_follow_the_maps_datum() -> None:
    from sogm_service.apps.viewer.hub import HubSettings, MapHub
    from sogm_service.core.geodesy import LocalTangentPlane
    from sogm_service.wire.messages import GeodeticFix
    from sogm_service.wire.queries import InfoReply

    datum = GeodeticFix(latitude=48.2, longitude=16.37, altitude=0.0)
    info = InfoReply(map="m", frame="map", server_id="s", resolution=RES, tile_size=256,
                     eps0=0.001, logodds_scale=1000.0, layers=["a", "b"], tiles=[(0, 0)],
                     bounds=(0.0, 0.0, 12.8, 12.8), datum=datum)
    msg = MapHub(HubSettings())._info_message(info)
    geo = msg["geo"]
    truth = LocalTangentPlane(datum).to_geodetic(130.0, -75.0)
    # what the page computes from the message for a cursor at (130, -75) m: first order at the
    # datum, within 1e-7 deg (about 1 cm) of the exact conversion this close to it
    assert geo["latitude"] - 75.0 * geo["deg_lat_per_m"] == pytest.approx(truth.latitude, abs=1e-7)
    assert geo["longitude"] + 130.0 * geo["deg_lon_per_m"] == pytest.approx(truth.longitude,
                                                                          abs=1e-7)
    # the legend's colours are the tiles' (render.class_colors, BGR there)
    from sogm_service.apps.render import class_colors

    assert msg["palette"] == ["#{:02x}{:02x}{:02x}".format(*c[::-1]) for c in class_colors(2)]
    assert msg["unknown"] == "#466e96"
