"""The ROS 2 adapters' error: a :class:`~sogm_service.wire.errors.DecodeError` whose code is
one of :data:`~sogm_service.wire.errors.ROS2_CODES`."""

from __future__ import annotations

from sogm_service.wire.errors import ROS2_CODES as REJECT_CODES
from sogm_service.wire.errors import DecodeError


class Ros2DecodeError(DecodeError):
    """A ROS 2 input refused: ``code`` (see :data:`REJECT_CODES`) and a sentence."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)


__all__ = ["REJECT_CODES", "Ros2DecodeError"]
