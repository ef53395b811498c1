"""Wire codec (codec.py + messages.py): round trips, one reason code per malformed case, fuzzing.

The server counts rejections per reason code, so each malformed case below checks the exact
code (and, where there is one, the offending field), not just that decoding failed.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from sogm_service.wire import codec, limits
from sogm_service.wire import compression as zstd
from sogm_service.wire.codec import SCHEMA_MODELS, DecodeError
from sogm_service.wire.errors import DECODE_CODES
from sogm_service.wire.messages import (
    DropLayersReply,
    ErrorReply,
    GeodeticFix,
    IsmAck,
    IsmHeader,
    IsmMessage,
    MatchReport,
    PoseMessage,
    PoseModel,
    RejectionReport,
    RobotTilesReply,
    TileEvent,
    WireArray,
)
from sogm_service.wire.queries import (
    FusedReply,
    FusedRequest,
    GridReply,
    InfoReply,
    StatsReply,
    SubmapRequest,
    SupercellNode,
    SupercellReply,
    SupercellRequest,
    TilesChangedRequest,
)

FUZZ = settings(max_examples=120, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow])


def ism_fields(**overrides: Any) -> dict[str, Any]:
    """A valid ISM as the plain map a robot would pack (3 x 2 occupancy grid)."""
    fields: dict[str, Any] = {
        "layer": "obstacle", "frame": "map", "stamp": 12.5, "robot": "r1",
        "resolution": 0.05, "origin": {"x": 1.0, "y": -2.0, "yaw": 0.3},
        "width": 3, "height": 2, "encoding": "occupancy_i8",
        "data": np.array([0, 50, 100, -1, 7, 93], np.int8).tobytes(),
    }
    fields.update(overrides)
    return fields


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def valid_instances() -> dict[type[BaseModel], BaseModel]:
    arr = WireArray.from_array(np.arange(24, dtype=np.int16).reshape(2, 3, 4))
    pose = PoseModel(x=1.0, y=2.0, yaw=-0.5)
    fix = GeodeticFix(latitude=52.03, longitude=8.49, altitude=110.0)
    instances: dict[type[BaseModel], BaseModel] = {
        IsmMessage: IsmMessage(**ism_fields()),
        PoseMessage: PoseMessage(robot="r1", frame="map", stamp=3.0, x=1.0, y=-1.0, yaw=0.1,
                                 fix=fix),
        SubmapRequest: SubmapRequest(x=1.0, y=2.0, yaw=0.5, width=4.0, height=3.0,
                                     resolution=0.1, layers=["a", "b"], interp="nearest",
                                     encoding="prob_f32"),
        FusedRequest: FusedRequest(layers=["a"], method="max", encoding="logodds_i16"),
        SupercellRequest: SupercellRequest(block_size=4, levels=2, bins=3, iterations=2,
                                           gamma=0.5, criterion="energy", labels=True),
        GridReply: GridReply(map="m", frame="map", stamp=1.0, resolution=0.1, origin=pose,
                             width=4, height=3, layers=["a", "b"], encoding="logodds_i16",
                             interp="biodds", data=arr),
        FusedReply: FusedReply(map="m", frame="map", stamp=1.0, resolution=0.1, origin=pose,
                               width=4, height=3, layers=["a", "b"], method="bayes",
                               encoding="prob_u8", interp="bilinear",
                               data=WireArray.from_array(np.zeros((3, 4), np.uint8))),
        SupercellReply: SupercellReply(
            map="m", frame="map", stamp=1.0, resolution=0.1, origin=pose, width=4, height=3,
            layers=["a"], nodes=[SupercellNode(id=0, x=0.1, y=0.2, area_cells=12,
                                               area_m2=0.12, neighbors=[1],
                                               logodds_sum=[-3.5], mean_probability=[0.3])],
            labels=WireArray.from_array(np.zeros((3, 4), np.int32))),
        TileEvent: TileEvent(map="m", robot="r1", i=-1, j=2, name="m/-1/2", origin=pose,
                             datum=fix, stamp=4.0),
        InfoReply: InfoReply(map="m", frame="map", server_id="s1", resolution=0.05,
                             tile_size=256, eps0=0.001, logodds_scale=1000.0, layers=["a"],
                             tiles=[(0, 0), (-1, 2)], bounds=(-12.8, 0.0, 12.8, 38.4),
                             datum=fix),
        StatsReply: StatsReply(map="m", server_id="s1", uptime_s=10.0,
                               counters={"isms_fused": 3}, rejected={"data_length": 1},
                               queue_depth=0, isms_per_s=0.3,
                               latency_ms={"fuse": {"p50": 1.5, "p99": 3.0}},
                               extra={"note": "x", "n": [1, 2]}),
        ErrorReply: ErrorReply(code="unknown_layer", message="no such layer",
                               parameter="layers"),
    }
    event = instances[TileEvent]
    instances[RobotTilesReply] = RobotTilesReply(map="m", robots=[event, event.model_copy(
        update={"robot": "r2", "datum": None})])
    instances[MatchReport] = MatchReport(
        map="m", key="ism/r1/laser/obstacle", layer="obstacle", robot="r1", stamp=5.0,
        mode="report", accepted=True, reason="ok", claimed=pose,
        corrected=PoseModel(x=1.1, y=2.0, yaw=-0.45), dx_m=0.1, dy_m=0.0, dyaw_rad=0.05,
        inliers=42, score_before=0.2, score_after=0.8, elapsed_ms=13.0)
    instances[RejectionReport] = RejectionReport(
        key="ism/r1/laser/obstacle", code="wrong_frame", message="ISM frame 'odom'",
        stamp=6.0, id="a1b2c3-7")
    instances[TilesChangedRequest] = TilesChangedRequest(x=1.0, y=-2.0, width=30.0, height=20.0,
                                                         held={"0,-1": 17, "3,2": 0})
    instances[IsmAck] = IsmAck(id="a1b2c3-7", status="rejected", key="ism/r1/laser/obstacle",
                               code="wrong_frame", message="ISM frame 'odom'", stamp=6.0)
    instances[DropLayersReply] = DropLayersReply(
        map="default", server_id="a1b2", pattern="robot2/*", layers=["robot2/laser/obstacle"],
        tiles_rewritten=3, tiles_removed=1, stored=True)
    return instances


def test_every_schema_model_has_a_valid_instance_here() -> None:
    assert set(valid_instances()) == set(SCHEMA_MODELS)


@pytest.mark.parametrize("model", SCHEMA_MODELS, ids=lambda m: m.__name__)
def test_round_trip(model: type[BaseModel]) -> None:
    instance = valid_instances()[model]
    payload = codec.encode(instance)
    assert isinstance(payload, bytes)
    decoded = codec.decode(model, payload)
    assert type(decoded) is model
    assert decoded == instance
    assert codec.encode(decoded) == payload  # and it is stable
    # bytearray / memoryview payloads (as zenoh may hand them over) decode the same
    assert codec.decode(model, memoryview(bytearray(payload))) == instance


def test_round_trip_keeps_array_bytes_and_ism_cells() -> None:
    reply = valid_instances()[GridReply]
    assert isinstance(reply, GridReply)
    back = codec.decode(GridReply, codec.encode(reply))
    np.testing.assert_array_equal(back.data.array(), np.arange(24, dtype=np.int16)
                                  .reshape(2, 3, 4))
    ism = codec.decode(IsmMessage, pack(ism_fields()))
    np.testing.assert_array_equal(ism.array(), [[0, 50, 100], [-1, 7, 93]])


def test_a_robot_may_leave_out_optional_fields_and_add_unknown_ones() -> None:
    fields = ism_fields(future_field={"x": 1})
    for optional in ("layer", "frame", "stamp", "robot", "origin"):
        del fields[optional]
    msg = codec.decode(IsmMessage, pack(fields))
    assert msg.layer is None and msg.frame == "map" and msg.origin == PoseModel()


# -- each malformed case, its own reason code ----------------------------------------------


def reject(model: type[BaseModel], payload: bytes, code: str,
           context: dict[str, Any] | None = None) -> DecodeError:
    with pytest.raises(DecodeError) as info:
        codec.decode(model, payload, context=context)
    assert info.value.code == code, str(info.value)
    assert code in DECODE_CODES
    assert str(info.value)  # a sentence for people
    return info.value


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x85\xa3abc", pack(ism_fields()) + b"\x00",
                                     b"\xd9\x03\xff\xfe\xfd", b"\x81\x01\x02"],
                         ids=["empty", "never-used-byte", "truncated", "trailing-data",
                              "bad-utf8", "int-map-key"])
def test_malformed_msgpack(payload: bytes) -> None:
    reject(IsmMessage, payload, "malformed_msgpack")


@pytest.mark.parametrize("obj", [[1, 2], 5, "ism", None, b"bytes", 1.5, True])
def test_not_a_map(obj: Any) -> None:
    reject(IsmMessage, pack(obj), "not_a_map")
    reject(PoseMessage, pack(obj), "not_a_map")


@pytest.mark.parametrize("field", ["resolution", "width", "height", "encoding", "data"])
def test_missing_field(field: str) -> None:
    fields = ism_fields()
    del fields[field]
    err = reject(IsmMessage, pack(fields), "missing_field")
    assert err.parameter == field


def test_missing_field_of_pose_and_nested() -> None:
    assert reject(PoseMessage, pack({"x": 1.0}), "missing_field").parameter == "y"
    fix = {"x": 1.0, "y": 1.0, "fix": {"latitude": 1.0}}
    assert reject(PoseMessage, pack(fix), "missing_field").parameter == "fix.longitude"


@pytest.mark.parametrize("field,value", [
    ("width", "3"), ("width", 3.0), ("width", True), ("height", [2]), ("data", 123),
    ("data", [1, 2, 3]), ("origin", "here"), ("origin", [1.0, 2.0, 0.0]), ("layer", 5),
    ("frame", b"map"), ("resolution", "fine"), ("resolution", [0.1]), ("stamp", {"s": 1}),
])
def test_wrong_type(field: str, value: Any) -> None:
    err = reject(IsmMessage, pack(ism_fields(**{field: value})), "wrong_type")
    assert err.parameter is not None and err.parameter.startswith(field)


def test_wrong_type_in_replies_and_requests() -> None:
    reply = codec.encode(valid_instances()[GridReply])
    obj = msgpack.unpackb(reply)
    obj["width"] = 3.5
    reject(GridReply, pack(obj), "wrong_type")
    obj["width"] = "wide"
    reject(GridReply, pack(obj), "wrong_type")
    reject(SupercellRequest, pack({"block_size": 2.5}), "wrong_type")
    reject(PoseMessage, pack({"x": 1.0, "y": 2.0, "fix": 7}), "wrong_type")


@pytest.mark.parametrize("encoding,itemsize", [("occupancy_i8", 1), ("prob_u8", 1),
                                               ("prob_f32", 4)])
@pytest.mark.parametrize("delta", [-1, 1, -6])
def test_data_length(encoding: str, itemsize: int, delta: int) -> None:
    n = 3 * 2 * itemsize + delta
    fields = ism_fields(encoding=encoding, data=bytes(max(n, 0)))
    reject(IsmMessage, pack(fields), "data_length")


def test_data_length_of_wire_arrays() -> None:
    obj = msgpack.unpackb(codec.encode(valid_instances()[GridReply]))
    obj["data"]["data"] = obj["data"]["data"][:-1]
    reject(GridReply, pack(obj), "data_length")
    obj["data"]["shape"] = [2, 3]
    reject(GridReply, pack(obj), "data_length")


@pytest.mark.parametrize("where", ["resolution", "stamp", "origin.x", "origin.yaw", "data"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite(where: str, bad: float) -> None:
    if where == "data":
        cells = np.array([0.1, 0.2, bad, 0.4, 0.5, 0.6], np.float32)
        fields = ism_fields(encoding="prob_f32", data=cells.tobytes())
        if math.isnan(bad):  # schema version 2: NaN in prob_f32 is "unknown", not an error
            assert np.isnan(codec.decode(IsmMessage, pack(fields)).array()).sum() == 1
            return
    elif where.startswith("origin."):
        fields = ism_fields(origin={"x": 0.0, "y": 0.0, "yaw": 0.0, where[7:]: bad})
    else:
        fields = ism_fields(**{where: bad})
    reject(IsmMessage, pack(fields), "non_finite")


def test_non_finite_pose() -> None:
    reject(PoseMessage, pack({"x": math.nan, "y": 0.0}), "non_finite")
    reject(PoseMessage, pack({"x": 0.0, "y": 0.0, "yaw": math.inf}), "non_finite")


@pytest.mark.parametrize("res", [0.0, -0.0, -0.05, -1e300, 0])
def test_non_positive_resolution(res: float) -> None:
    err = reject(IsmMessage, pack(ism_fields(resolution=res)), "non_positive_resolution")
    assert err.parameter == "resolution"


@pytest.mark.parametrize("encoding,cells", [
    ("prob_f32", np.array([0.1, 0.2, 1.0001, 0.4, 0.5, 0.6], np.float32)),
    ("prob_f32", np.array([0.1, -1e-6, 0.3, 0.4, 0.5, 0.6], np.float32)),
    ("occupancy_i8", np.array([0, 50, 101, -1, 7, 93], np.int8)),
    ("occupancy_i8", np.array([0, -2, 100, -1, 7, 93], np.int8)),
    ("occupancy_i8", np.array([127, -128, 100, -1, 7, 93], np.int8)),
])
def test_out_of_range(encoding: str, cells: np.ndarray) -> None:
    reject(IsmMessage, pack(ism_fields(encoding=encoding, data=cells.tobytes())), "out_of_range")


def test_boundary_values_are_in_range() -> None:
    for encoding, cells in [("prob_f32", np.array([0, 1, 0.5, 0, 1, 0], np.float32)),
                            ("occupancy_i8", np.array([0, 100, -1, 0, 100, -1], np.int8)),
                            ("prob_u8", np.array([0, 255, 128, 0, 255, 1], np.uint8))]:
        msg = codec.decode(IsmMessage, pack(ism_fields(encoding=encoding,
                                                       data=cells.tobytes())))
        np.testing.assert_array_equal(msg.array().ravel(), cells)


def test_too_large_by_configurable_cell_limit() -> None:
    payload = pack(ism_fields())  # 6 cells
    reject(IsmMessage, payload, "too_large", context={"max_cells": 5})
    assert codec.decode(IsmMessage, payload, context={"max_cells": 6}).width == 3
    # a huge declared size is refused for its size, before its (short) data is looked at
    huge = pack(ism_fields(width=100_000, height=100_000, data=b"\x00"))
    reject(IsmMessage, huge, "too_large")


def test_too_large_payload_bytes() -> None:
    with pytest.raises(DecodeError) as info:
        codec.unpack(pack(ism_fields()), max_bytes=10)
    assert info.value.code == "too_large"


def test_invalid_values_are_invalid_value() -> None:
    reject(IsmMessage, pack(ism_fields(width=0)), "invalid_value")
    reject(IsmMessage, pack(ism_fields(height=-3)), "invalid_value")
    reject(IsmMessage, pack(ism_fields(encoding="logodds_i16")), "invalid_value")
    reject(PoseMessage, pack({"x": 0.0, "y": 0.0, "fix": {"latitude": 91.0,
                                                          "longitude": 0.0}}), "invalid_value")
    reject(SubmapRequest, pack({"interp": "cubic"}), "invalid_value")
    reject(SubmapRequest, pack({"width": -1.0}), "invalid_value")
    reject(SubmapRequest, pack({"widht": 1.0}), "invalid_value")  # typos are refused


# -- fuzzing: nothing but DecodeError, and every code is a documented one ------------------

msgpack_objects = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8)
    | st.binary(max_size=16)
    | st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=4)),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=8) | st.binary(max_size=4), children, max_size=4),
    max_leaves=12,
)
model_classes = st.sampled_from(SCHEMA_MODELS)


def decodes_or_rejects(model: type[BaseModel], payload: bytes,
                       context: dict[str, Any] | None = None) -> BaseModel | None:
    try:
        return codec.decode(model, payload, context=context)
    except DecodeError as exc:
        assert exc.code in DECODE_CODES, (exc.code, str(exc))
        return None


@FUZZ
@given(model=model_classes, payload=st.binary(max_size=64))
def test_random_bytes_only_raise_decode_error(model: type[BaseModel], payload: bytes) -> None:
    decodes_or_rejects(model, payload)


@FUZZ
@given(model=model_classes, obj=msgpack_objects)
def test_random_msgpack_objects_only_raise_decode_error(model: type[BaseModel],
                                                        obj: Any) -> None:
    decodes_or_rejects(model, pack(obj))


@FUZZ
@given(model=model_classes, data=st.data())
def test_field_mutations_only_raise_decode_error(model: type[BaseModel],
                                                 data: st.DataObject) -> None:
    obj = msgpack.unpackb(codec.encode(valid_instances()[model]))
    keys = sorted(obj)
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from([*keys, "extra"]))
        if data.draw(st.booleans()) and key in obj:
            del obj[key]
        else:
            obj[key] = data.draw(msgpack_objects)
    decodes_or_rejects(model, pack(obj), context={"max_cells": 1000})


@FUZZ
@given(model=model_classes, data=st.data())
def test_byte_mutations_only_raise_decode_error(model: type[BaseModel],
                                                data: st.DataObject) -> None:
    payload = bytearray(codec.encode(valid_instances()[model]))
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        pos = data.draw(st.integers(0, max(len(payload) - 1, 0)))
        if op == "flip" and payload:
            payload[pos] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "insert":
            payload[pos:pos] = data.draw(st.binary(min_size=1, max_size=4))
        elif op == "delete" and payload:
            del payload[pos]
        else:
            del payload[pos:]
    decodes_or_rejects(model, bytes(payload))


@FUZZ
@given(data=st.data())
def test_mutated_ism_cells_are_accepted_only_when_valid(data: st.DataObject) -> None:
    encoding = data.draw(st.sampled_from(["occupancy_i8", "prob_u8", "prob_f32"]))
    itemsize = 4 if encoding == "prob_f32" else 1
    raw = data.draw(st.binary(min_size=6 * itemsize, max_size=6 * itemsize))
    msg = decodes_or_rejects(IsmMessage, pack(ism_fields(encoding=encoding, data=raw)))
    if msg is not None:  # accepted cells are safe for the core
        assert isinstance(msg, IsmMessage)
        a = msg.array()
        if encoding == "prob_f32":
            assert np.isfinite(a).all() and (a >= 0).all() and (a <= 1).all()
        elif encoding == "occupancy_i8":
            assert ((a >= -1) & (a <= 100)).all()


def test_reject_codes_are_documented() -> None:
    assert set(DECODE_CODES) >= {
        "malformed_msgpack", "not_a_map", "missing_field", "wrong_type", "data_length",
        "non_finite", "non_positive_resolution", "out_of_range", "too_large"}
    assert limits.MAX_ISM_CELLS >= 4096 * 4096 // 4


# -- robots' messages are strict: no silent coercion of booleans, strings or text ---------


@pytest.mark.parametrize("field,value", [("resolution", True), ("resolution", "0.05"),
                                         ("stamp", b"12"), ("data", "\x00" * 6)])
def test_lax_coercions_are_refused(field: str, value: Any) -> None:
    reject(IsmMessage, pack(ism_fields(**{field: value})), "wrong_type")


def ism_payload(data: np.ndarray, encoding: str, res: float = 0.05) -> bytes:
    """An ISM packed from the schema's fields (schemas/ism.json), not the project's model."""
    return msgpack.packb({"resolution": res, "origin": {"x": 0.0, "y": 0.0, "yaw": 0.0},
                          "width": int(data.shape[1]), "height": int(data.shape[0]),
                          "encoding": encoding, "data": np.ascontiguousarray(data).tobytes()})


def test_wire_accepts_every_prob_u8_v2_code_and_nan_but_not_infinity() -> None:
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    msg = codec.decode(IsmMessage, ism_payload(codes, "prob_u8_v2"))
    assert msg.array().tolist() == codes.tolist()
    cells = np.array([[0.2, np.nan], [1.0, 0.0]], np.float32)
    assert np.isnan(codec.decode(IsmMessage, ism_payload(cells, "prob_f32")).array()).sum() == 1
    for bad, code in (([np.inf, 0.5], "non_finite"), ([np.nan, 1.5], "out_of_range"),
                      ([np.nan, -0.1], "out_of_range")):
        with pytest.raises(DecodeError) as info:
            codec.decode(IsmMessage, ism_payload(np.array([bad], np.float32), "prob_f32"))
        assert info.value.code == code


def test_framing_only_checks_a_zstd_frame_from_its_header_and_keeps_it() -> None:
    """``framing_only``: what a cluster member that owns none of an ISM's tiles checks.  A
    frame that declares the right size is kept as sent, undecompressed; its content is the
    full check's.  A wrong declared size, a frame that is not zstd and raw cells are refused
    alike in both."""
    cells = np.array([0, 50, 100, -1, 7, 93], np.int8).tobytes()
    framing = {"framing_only": True}
    cut_short = zstd.compress(cells)[:-3]
    sent = codec.decode(IsmMessage, pack(ism_fields(data=cut_short, compression="zstd")),
                        context=framing)
    assert sent.compression == "zstd" and sent.data == cut_short
    reject(IsmMessage, pack(ism_fields(data=cut_short, compression="zstd")), "bad_compression")
    for context in (framing, None):
        reject(IsmMessage, pack(ism_fields(data=zstd.compress(cells + b"\0"),
                                           compression="zstd")), "data_length", context)
        reject(IsmMessage, pack(ism_fields(data=b"not a zstd frame", compression="zstd")),
               "bad_compression", context)
        reject(IsmMessage, pack(ism_fields(data=cells[:-1])), "data_length", context)
        reject(IsmMessage, pack(ism_fields(data=np.array([101] * 6, np.int8).tobytes())),
               "out_of_range", context)
    assert set(IsmHeader.model_fields) == set(IsmMessage.model_fields) - {"data", "compression"}
