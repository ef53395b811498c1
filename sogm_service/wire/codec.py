"""msgpack codec of the wire models: bytes in, validated model out, or a :class:`DecodeError`.

No pickle, no ext types: a payload is a msgpack map of the model's fields, bytes as msgpack
``bin``.  Decoding never raises anything but :class:`DecodeError`, whose ``code`` names the
reason (see :data:`sogm_service.wire.errors.DECODE_CODES`) so that the server can count rejections
per reason.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from sogm_service.wire import messages as m
from sogm_service.wire import queries as q
from sogm_service.wire.errors import DECODE_CODES, DecodeError
from sogm_service.wire.limits import MAX_MSGPACK_STR, MAX_PAYLOAD_BYTES
from sogm_service.wire.messages import SCHEMA_VERSION

M = TypeVar("M", bound=BaseModel)

SCHEMA_MODELS: tuple[type[BaseModel], ...] = (
    m.IsmMessage, m.PoseMessage, q.SubmapRequest, q.FusedRequest, q.SupercellRequest,
    q.GridReply, q.FusedReply, q.SupercellReply, m.TileEvent, m.RobotTilesReply, m.MatchReport,
    q.InfoReply, q.StatsReply, m.ErrorReply, m.RejectionReport, m.IsmAck, q.TilesChangedRequest,
    m.DropLayersReply,
)
"""Every wire model with a JSON Schema in ``schemas/`` (``sogm-service schemas``)."""

# pydantic's built-in error types -> our reject codes.
_PYDANTIC_CODES = {
    "missing": "missing_field",
    "finite_number": "non_finite",
    "literal_error": "invalid_value",
    "enum": "invalid_value",
    "greater_than": "invalid_value",
    "greater_than_equal": "invalid_value",
    "less_than": "invalid_value",
    "less_than_equal": "invalid_value",
    "extra_forbidden": "invalid_value",
    "int_from_float": "wrong_type",  # 1.5 where an integer belongs
    "string_unicode": "wrong_type",  # bytes that are not UTF-8 where a string belongs
}

def encode(model: BaseModel) -> bytes:
    """Model -> msgpack bytes."""
    packed = msgpack.packb(model.model_dump(mode="python"), use_bin_type=True)
    assert isinstance(packed, bytes)
    return packed


def unpack(payload: bytes | bytearray | memoryview, max_bytes: int = MAX_PAYLOAD_BYTES) -> Any:
    """msgpack bytes -> Python objects, or :class:`DecodeError` (``malformed_msgpack``)."""
    if len(payload) > max_bytes:
        raise DecodeError("too_large", f"payload of {len(payload)} bytes exceeds {max_bytes}")
    try:
        return msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True,
                               max_bin_len=max_bytes, max_str_len=MAX_MSGPACK_STR)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise DecodeError("malformed_msgpack", f"payload is not valid msgpack: {exc}") from None


def validate(cls: type[M], obj: Any, context: dict[str, Any] | None = None) -> M:
    """Python objects -> a validated model, or :class:`DecodeError` naming the first problem."""
    if not isinstance(obj, dict):
        raise DecodeError("not_a_map", f"{cls.__name__} must be a map, got {type(obj).__name__}")
    try:
        return cls.model_validate(obj, context=context)
    except ValidationError as exc:
        raise validation_error_to_decode_error(exc) from None
    except (TypeError, ValueError, OverflowError) as exc:  # defensive: never escape as-is
        raise DecodeError("invalid_value", str(exc)) from None


def validation_error_to_decode_error(exc: ValidationError) -> DecodeError:
    err = exc.errors(include_url=False)[0]
    kind = str(err["type"])
    loc = ".".join(str(p) for p in err["loc"])
    if kind in _PYDANTIC_CODES:
        code = _PYDANTIC_CODES[kind]
    elif kind.endswith("_type") or kind.endswith("_parsing") or kind == "model_type":
        code = "wrong_type"
    elif kind in DECODE_CODES:
        code = kind  # our own PydanticCustomError codes
    else:
        code = "invalid_value"  # any other pydantic check: never an undocumented code
    where = f"{loc}: " if loc else ""
    return DecodeError(code, f"{where}{err['msg']}", parameter=loc or None)


def decode(cls: type[M], payload: bytes | bytearray | memoryview,
           context: dict[str, Any] | None = None) -> M:
    """msgpack bytes -> a validated ``cls``, or :class:`DecodeError`."""
    return validate(cls, unpack(payload), context)


def json_schemas() -> dict[str, dict[str, Any]]:
    """JSON Schema of every wire message, keyed by file stem."""
    out: dict[str, dict[str, Any]] = {}
    for model in SCHEMA_MODELS:
        name = getattr(model, "schema_name", "") or model.__name__
        schema = model.model_json_schema()
        schema["$id"] = f"https://sogm-service/schemas/{name}.json"
        schema["x-sogm-schema-version"] = SCHEMA_VERSION
        out[name] = schema
    return out


def render_schema(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


def write_schemas(directory: Path) -> list[Path]:
    """Write ``<name>.json`` for every message into ``directory``; returns the paths."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in json_schemas().items():
        path = directory / f"{name}.json"
        path.write_text(render_schema(schema), encoding="utf-8")
        written.append(path)
    return written


def stale_schemas(directory: Path) -> list[str]:
    """Names whose file in ``directory`` is missing or differs from the models."""
    stale = []
    for name, schema in json_schemas().items():
        path = directory / f"{name}.json"
        if not path.exists() or path.read_text(encoding="utf-8") != render_schema(schema):
            stale.append(name)
    return stale
