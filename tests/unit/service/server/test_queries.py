"""Query parsing and answering, in process (service/server/queries.py): parameters typed
strictly, each given once; glob patterns in ``layers`` answered as classes of a real
:class:`TiledMap` (fused by the Bayesian rule), their members sampled once and priced."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D, TileLattice
from sogm_service.core.map.tiles import TiledMap
from sogm_service.service.server import queries
from sogm_service.wire.errors import QueryError
from sogm_service.wire.queries import (
    FusedRequest,
    SubmapRequest,
    SupercellRequest,
    TilesChangedRequest,
    selector_params,
    unpack_body,
)

RES = 0.1


def _refused(call: Any, *args: Any) -> QueryError:
    with pytest.raises(QueryError) as err:
        call(*args)
    return err.value


@pytest.mark.parametrize(("params", "body", "parameter"), [
    ({}, {"width": True}, "width"),
    ({}, {"width": "2"}, "width"),
    ({}, {"height": None}, "height"),
    ({"width": "true"}, None, "width"),
    ({"width": "2"}, {"width": 2}, "width"),  # once in the selector, once in the body
    ({"layers": "a b"}, None, "layers.0"),
    ({}, {"layers": ["x" * 129]}, "layers.0"),
    ({}, {"layers": [f"l{k}" for k in range(257)]}, "layers"),
])
def test_loose_or_repeated_parameters_are_bad(params: dict[str, str], body: Any,
                                              parameter: str) -> None:
    raw = None if body is None else msgpack.packb(body)
    err = _refused(queries.parse_request, SubmapRequest, params, raw)
    assert (err.code, err.parameter) == ("bad_parameter", parameter)


def test_selector_strings_take_their_fields_types() -> None:
    req = queries.parse_request(SupercellRequest, {"width": "2.5", "block_size": "4",
                                                   "labels": "true", "layers": "*/a,b"},
                                msgpack.packb({"height": 3, "gamma": 0.5}))
    assert (req.width, req.height, req.block_size, req.labels) == (2.5, 3.0, 4, True)
    assert req.layers == ["*/a", "b"] and req.gamma == 0.5
    for body in ({"block_size": 4.0}, {"labels": 1}, {"iterations": True}):
        assert _refused(queries.parse_request, SupercellRequest, {},
                        msgpack.packb(body)).code == "bad_parameter"
    changed = queries.parse_request(TilesChangedRequest, {"i0": "1"},
                                    msgpack.packb({"held": [[1, 2, 3]]}))
    assert changed.i0 == 1 and changed.held == [(1, 2, 3)]
    assert _refused(queries.parse_request, TilesChangedRequest, {},
                    msgpack.packb({"held": {"0,0": True}})).code == "bad_parameter"


def test_repeats_in_the_selector_and_the_body() -> None:
    err = _refused(selector_params, [("width", "1"), ("x", "0"), ("width", "2")])
    assert (err.code, err.parameter) == ("bad_parameter", "width")
    assert selector_params([("_anyke", ""), ("x", "1")]) == {"x": "1"}  # Zenoh's own
    err = _refused(unpack_body, b"\x82\xa5width\x01\xa5width\x02")
    assert (err.code, err.parameter) == ("bad_parameter", "width")
    nested = b"\x81\xa4held\x82\xa30,0\x01\xa30,0\x02"  # {"held": {"0,0": 1, "0,0": 2}}
    assert _refused(unpack_body, nested).parameter == "0,0"
    for junk in (b"\xc1", msgpack.packb([1, 2]), msgpack.packb({1: 2})):
        assert _refused(unpack_body, junk).code == "bad_parameter"


def _map() -> TiledMap:
    """robot1 alone at x < 0, robot2 alone at x >= 0.5, both in [0, 0.5); a camera layer."""
    tiled = TiledMap("m", "map", TileLattice(RES, 64))
    for layer, p, x0, w in (("robot1/laser/obstacle", 0.7, -2.0, 25),
                            ("robot2/laser/obstacle", 0.8, 0.0, 20),
                            ("robot1/camera/person", 0.9, -2.0, 20)):
        geom = GridGeometry(RES, w, 10, Pose2D(x0, -0.5, 0.0))
        tiled.fuse(layer, logodds.prob_to_fixed(np.full((10, w), p)), geom, "nearest")
    return tiled


WINDOW = {"x": "0", "y": "0", "width": "4", "height": "1", "interp": "nearest",
          "encoding": "logodds_i16"}


def test_a_pattern_is_one_plane_of_its_members_fused() -> None:
    tiled = _map()
    req = queries.parse_request(SubmapRequest, dict(WINDOW, layers="*/laser/obstacle"))
    reply = queries.submap(tiled, req, 0.0)
    per = queries.submap(tiled, queries.parse_request(SubmapRequest, dict(
        WINDOW, layers="robot1/laser/obstacle,robot2/laser/obstacle")), 0.0)
    assert reply.layers == ["*/laser/obstacle"] and per.classes is None
    assert reply.classes == {"*/laser/obstacle": ["robot1/laser/obstacle",
                                                  "robot2/laser/obstacle"]}
    plane, (r1, r2) = reply.data.array()[0], per.data.array().astype(np.int32)
    lo, hi = logodds.clamp_limits()
    assert np.array_equal(plane, np.clip(r1 + r2, lo, hi))
    assert (r1[:, :20] != 0).all() and (r2[:, :20] == 0).all()  # the areas differ...
    assert (r1[:, 25:] == 0).all() and (r2[:, 25:40] != 0).all()
    assert (plane[:, 20:25] == r1[:, 20:25] + r2[:, 20:25]).all()  # ...and overlap here


def test_fused_over_patterns_pools_the_classes() -> None:
    tiled = _map()
    classes = queries.submap(tiled, queries.parse_request(SubmapRequest, dict(
        WINDOW, layers="*/laser/*,*/camera/*")), 0.0).data.array().astype(np.int32)
    fused = queries.fused(tiled, queries.parse_request(FusedRequest, dict(
        WINDOW, layers="*/laser/*,*/camera/*")), 0.0)
    assert fused.layers == ["*/laser/*", "*/camera/*"]
    assert np.array_equal(fused.data.array(), classes.sum(axis=0))


def test_an_unmatched_pattern_or_name_is_unknown_layer() -> None:
    tiled = _map()
    for layers in ("*/lidar/*", "robot1/laser/obstacle,robot9/laser/obstacle"):
        req = queries.parse_request(SubmapRequest, dict(WINDOW, layers=layers))
        err = _refused(queries.submap, tiled, req, 0.0)
        assert (err.code, err.parameter) == ("unknown_layer", "layers")


class _Pricing:
    """An admission that records what it is asked to price."""

    def __init__(self) -> None:
        self.asked: list[tuple[int, int | None]] = []

    def check_query(self, req: Any, n_layers: int, reply_layers: int | None = None) -> None:
        self.asked.append((n_layers, reply_layers))


def test_a_class_is_priced_by_its_members_read_and_one_plane_replied() -> None:
    tiled, pricing = _map(), _Pricing()
    req = queries.parse_request(SubmapRequest, dict(WINDOW, layers="robot*/*,*/laser/*"))
    reply = queries.submap(tiled, req, 0.0, admission=pricing)  # type: ignore[arg-type]
    assert pricing.asked == [(3, 2)] and reply.data.array().shape[0] == 2
