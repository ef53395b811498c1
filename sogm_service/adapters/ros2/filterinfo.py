"""CDR of ``nav2_msgs/msg/CostmapFilterInfo`` through rosbags (pure, no zenoh).

rosbags' Jazzy typestore has no nav2_msgs, so the type is registered from its definition text
(:data:`COSTMAP_FILTER_INFO_MSG`); its RIHS01 hash is what rosbags computes from it
(:data:`~sogm_service.adapters.ros2.keys.TYPE_HASHES`).  nav2's costmap filters subscribe to it
transient-local and read ``filter_mask_topic``, ``type`` and ``base + multiplier * value``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from rosbags.typesys import get_types_from_msg
from rosbags.typesys.store import Typestore

from sogm_service.adapters.ros2 import cdr
from sogm_service.adapters.ros2.errors import Ros2DecodeError
from sogm_service.adapters.ros2.keys import COSTMAP_FILTER_INFO

COSTMAP_FILTER_INFO_MSG = """std_msgs/Header header
uint8 type
string filter_mask_topic
float32 base
float32 multiplier
"""
"""``nav2_msgs/msg/CostmapFilterInfo``'s definition (its comments left out: they do not enter
the type hash)."""

MAX_FILTER_INFO_BYTES = 1 << 16


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The bridge's typestore (:func:`~sogm_service.adapters.ros2.cdr.typestore`) with
    CostmapFilterInfo registered."""
    ts = cdr.typestore()
    if COSTMAP_FILTER_INFO not in ts.types:
        ts.register(get_types_from_msg(COSTMAP_FILTER_INFO_MSG, COSTMAP_FILTER_INFO))
    return ts


@dataclass(frozen=True)
class FilterInfoFields:
    """A CostmapFilterInfo, flat."""

    frame: str
    stamp: float
    type: int
    filter_mask_topic: str
    base: float
    multiplier: float

    def same_content(self, other: FilterInfoFields | None) -> bool:
        """Equal but for the stamp: a filter info that did not change is not sent again."""
        return other is not None and (self.frame, self.type, self.filter_mask_topic,
                                      self.base, self.multiplier) == \
            (other.frame, other.type, other.filter_mask_topic, other.base, other.multiplier)


def encode_filter_info(f: FilterInfoFields) -> bytes:
    ts = typestore()
    msg = ts.types[COSTMAP_FILTER_INFO](
        header=cdr._header(f.frame, f.stamp), type=int(f.type),
        filter_mask_topic=f.filter_mask_topic, base=float(f.base),
        multiplier=float(f.multiplier))
    return bytes(ts.serialize_cdr(msg, COSTMAP_FILTER_INFO))


def decode_filter_info(payload: bytes | bytearray | memoryview, *,
                       max_bytes: int = MAX_FILTER_INFO_BYTES) -> FilterInfoFields:
    if len(payload) > max_bytes:
        raise Ros2DecodeError("too_large", f"CostmapFilterInfo payload of {len(payload)} "
                                           f"bytes exceeds {max_bytes}")
    try:
        m: Any = typestore().deserialize_cdr(bytes(payload), COSTMAP_FILTER_INFO)
    except Exception as exc:  # rosbags raises SerdeError; be defensive about the rest
        raise Ros2DecodeError("bad_cdr", f"not a CDR {COSTMAP_FILTER_INFO}: {exc}") from None
    stamp = float(m.header.stamp.sec) + float(m.header.stamp.nanosec) * 1e-9
    return FilterInfoFields(str(m.header.frame_id), stamp, int(m.type),
                            str(m.filter_mask_topic), float(m.base), float(m.multiplier))
