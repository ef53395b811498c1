"""The one error type of the ROS 2 adapters: a specific ``code`` per reason, as the wire layer's."""

from __future__ import annotations

REJECT_CODES: dict[str, str] = {
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


class Ros2DecodeError(ValueError):
    """A ROS 2 input refused: ``code`` (a short string, see :data:`REJECT_CODES`) and a sentence.

    ``parameter`` is always ``None``; it is there so that callers can treat this error like the
    wire layer's :class:`~sogm_service.wire.codec.DecodeError`.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.parameter: str | None = None
