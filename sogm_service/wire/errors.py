"""Every error the service and its client raise, and every reason code, in one place.

One base, :class:`SogmError`, carries what the wire needs to report a refusal: a
machine-readable ``code`` (counted per reason in ``stats`` and sent back with ``reply_err``), a
sentence for people (``message``) and the ``parameter`` at fault when there is one.  The
families below differ only in where the refusal happens, so a handler can catch the base.
"""

from __future__ import annotations

from typing import Final

DECODE_CODES: Final[dict[str, str]] = {
    "malformed_msgpack": "the payload is not valid msgpack",
    "not_a_map": "the payload is not a msgpack map",
    "missing_field": "a required field is missing",
    "wrong_type": "a field has the wrong type",
    "data_length": "the data length does not match width x height x encoding",
    "bad_compression": "compressed data is not one zstd frame declaring its size",
    "non_finite": "a number is NaN or infinite",
    "non_positive_resolution": "the resolution is not positive",
    "out_of_range": "a probability or occupancy value is out of range",
    "too_large": "the message exceeds the configured size limits",
    "invalid_value": "a field has an invalid value",
}
"""Why a payload is not a valid message (:class:`DecodeError`)."""

ISM_CODES: Final[dict[str, str]] = {
    "wrong_frame": "the ISM's frame is not the map frame",
    "bad_layer": "the layer name is empty, too long or has characters outside [A-Za-z0-9_-./]",
    "too_large": "the ISM's footprint covers more tiles than the limit",
    "robot_mismatch": "the message names another robot than its key (ism/<robot>/..., "
                      "pose/<robot>)",
    "internal_error": "the server failed on this ISM (a bug: the map is unchanged)",
    "out_of_world": "a corner of the ISM lies outside the configured world extent around the "
                    "map origin",
    "too_many_layers": "the ISM would add a layer beyond the map's layer limit",
    "too_many_robots": "the ISM's robot would be one more than the robots tracked limit",
    "name_too_long": "the robot or layer name is longer than its limit",
    "memory_budget": "the ISM would create tiles beyond the memory budget of a map without a "
                     "tile store",
    "stale_stamp": "the ISM's stamp is so far behind the map's clock that its forgetting "
                   "layer would keep nothing of it (stamps are Unix time in seconds)",
}
"""Why a well-formed ISM cannot go into this map (:class:`IsmRejectedError`); scan matching adds
``match_<reason>`` (:class:`sogm_service.core.matching.params.MatchReason`)."""

ROS2_CODES: Final[dict[str, str]] = {
    "bad_cdr": "the payload is not a CDR serialisation of the expected ROS 2 type",
    "too_large": "the message exceeds the configured size limits",
    "data_length": "the grid's data length is not width x height",
    "out_of_range": "an occupancy value is outside 0..100 and -1",
    "non_finite": "a number is NaN or infinite",
    "non_positive_resolution": "the grid resolution is not positive",
    "invalid_value": "a field has an invalid value",
    "bad_quaternion": "a quaternion has (nearly) zero length",
    "non_planar": "a quaternion is not a rotation about z",
    "bad_attachment": "the sample carries no valid rmw_zenoh attachment",
    "bad_key": "the key expression is not an rmw_zenoh data key",
    "wrong_type": "the key names another ROS type than the one expected",
    "type_hash": "the key's type hash is not the one this server knows for the type",
    "humble_disabled": "a Humble sample (TypeHashNotSupported) while Humble support is off",
    "bad_layer": "the topic gives an empty or invalid layer name",
    "wrong_frame": "a frame id is not the configured one",
    "too_many_frames": "the transform tree exceeds its frame limit",
}
"""Why a ROS 2 sample (rmw_zenoh wire: CDR, attachment, key) is refused
(:class:`sogm_service.adapters.ros2.errors.Ros2DecodeError`)."""

QUERY_CODES: Final[dict[str, str]] = {
    "bad_parameter": "a query parameter is missing, of the wrong type or out of range",
    "unknown_layer": "a requested layer does not exist",
    "window_too_large": "the window needs more cells than the limit",
    "internal_error": "the server failed on this query (a bug)",
    "out_of_world": "the window lies (partly) outside the configured world extent",
    "reply_too_large": "the reply would exceed the reply byte limit",
    "busy": "too many heavy queries run at once; retry after retry_after_s",
    "no_owner": "no live owner of a tile the window needs answered in time (cluster)",
    "warming_up": "the server is still compiling its supercell kernels (only after a fresh "
                  "install or upgrade); the client retries within its supercells timeout",
    "cluster_unsupported": "a cluster member does not drop layers (each member holds its share "
                           "and replicas: a drop on one would come back from another)",
}
"""Why a query cannot be answered (:class:`QueryError`)."""

POSE_CODES: Final[dict[str, str]] = {
    "robot_mismatch": "the pose names another robot than its key",
    "out_of_world": "the pose lies outside the configured world extent",
    "too_many_robots": "the pose's robot would be one more than the robots tracked limit",
    "name_too_long": "the robot name is longer than its limit",
}
"""Why a well-formed pose is refused (counted as ``poses_rejected_<code>``; decoding failures
use :data:`DECODE_CODES`)."""


class SogmError(Exception):
    """Base of every refusal: ``code``, ``message`` (for people) and ``parameter`` at fault."""

    def __init__(self, code: str, message: str, parameter: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.parameter = parameter


class DecodeError(SogmError, ValueError):
    """A payload that is not a valid message (codes: :data:`DECODE_CODES`)."""


class IsmRejectedError(SogmError, ValueError):
    """An ISM that is well-formed on the wire but cannot go into this map (:data:`ISM_CODES`)."""


class QueryError(SogmError, ValueError):
    """A query that cannot be answered (codes: :data:`QUERY_CODES`)."""


class BusyError(QueryError):
    """Too many heavy queries at once: ``busy``, with a retry hint in seconds."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__("busy", message)
        self.retry_after_s = retry_after_s


class ConfigError(SogmError, ValueError):
    """A configuration that cannot be used: says which field and why."""

    def __init__(self, message: str, parameter: str | None = None) -> None:
        super().__init__("bad_config", message, parameter)


class TileFormatError(SogmError, ValueError):
    """A tile file or blob that must not be loaded; ``reason`` says why, for a person."""

    def __init__(self, reason: str) -> None:
        super().__init__("bad_tile", reason)
        self.reason = reason


class StoreLockedError(SogmError, RuntimeError):
    """Another process owns the store directory (``directory``; ``pid`` of the holder when
    its lock file names one)."""

    def __init__(self, message: str, directory: str | None = None,
                 pid: int | None = None) -> None:
        super().__init__("store_locked", message)
        self.directory = directory
        self.pid = pid


class StoreUnavailableError(SogmError, RuntimeError):
    """The tile store cannot be reached or read (an object store's endpoint, bucket or
    credentials): the server does not start without the map it would serve."""

    def __init__(self, message: str) -> None:
        super().__init__("store_unavailable", message)


class StoreConflictError(SogmError, RuntimeError):
    """A tile write refused by a shared store: the stored tile changed since this server last
    saw it and holds an ISM this server's copy lacks (another server owns it now)."""

    def __init__(self, message: str, index: tuple[int, int]) -> None:
        super().__init__("store_conflict", message)
        self.index = index


class ClientError(RuntimeError):
    """Base of every error the Python client raises."""


class ServiceError(SogmError, ClientError):
    """The server refused the request: ``code`` (machine-readable), ``parameter`` at fault;
    ``retry_after_s`` with ``busy``."""

    retry_after_s: float | None = None

    def __str__(self) -> str:
        return f"[{self.code}] {self.message}"


class QueryTimeoutError(ClientError):
    """No server answered within the timeout."""


class SessionOpenError(SogmError, RuntimeError):
    """A Zenoh session could not be opened (a bad endpoint or config, nothing to connect to)."""

    def __init__(self, message: str, parameter: str | None = None) -> None:
        super().__init__("session_open", message, parameter)


class ConnectError(SessionOpenError, ClientError):
    """The client found no sogm-service (or router) at its endpoint, or its endpoint or Zenoh
    config is unusable."""


class InvalidIsmError(ClientError, ValueError):
    """An ISM the client refuses to publish (not a 2-D grid, a dtype that does not fit its
    encoding, an invalid field): nothing was sent."""


class IsmNotFusedError(ServiceError):
    """The server rejected a published ISM (``code`` as in :data:`DECODE_CODES` /
    :data:`ISM_CODES`; ``key`` is the ISM's key)."""

    def __init__(self, code: str, message: str, key: str) -> None:
        super().__init__(code, message)
        self.key = key

    def __str__(self) -> str:
        return f"the server rejected the ISM on {self.key} [{self.code}]: {self.message}"
