"""The encodings every Zenoh payload of the service declares, so that a generic Zenoh tool can
tell what it holds (without them every payload is ``zenoh/bytes``).

- :data:`MSGPACK`: every wire model (ISMs, poses, query replies, error replies, tile events,
  acks, rejection and match reports): a msgpack map of the model's fields
  (:mod:`sogm_service.wire.codec`); JSON Schemas of the models are in ``schemas/``.
- :data:`TILE`: a whole tile in the store's file format (:mod:`sogm_service.store.format`:
  magic, version, a JSON header with its CRC-32, then zlib of the raw ``<i2`` layers), as
  ``sogm/<map>/tiles/<i>/<j>`` answers it.
- either, compressed when the asker wants it (``compression=zstd``): the same bytes as one zstd
  frame, with the schema :data:`ZSTD_SCHEMA` (``application/msgpack;zstd``).

ROS 2 samples (rmw_zenoh's CDR) keep rmw_zenoh's own convention: no encoding is set, as ROS 2
nodes themselves send them.
"""

from __future__ import annotations

MSGPACK = "application/msgpack"
"""A msgpack-encoded wire model (the IANA-style name msgpack's own documentation uses)."""

TILE = "application/x-sogm-tile"
"""A tile file of the store's format (private subtype: no registered type exists for it)."""

ZSTD_SCHEMA = "zstd"
"""The schema suffix of a payload sent as one zstd frame (``application/msgpack;zstd``): a
client that asked for ``compression=zstd`` decompresses what declares it."""
