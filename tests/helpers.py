"""Helpers shared by unit and integration tests: the public data sets they read, and a plain
Zenoh session (no project code) for tests that read the wire as a third party would."""

from __future__ import annotations

import json

import pytest
import zenoh

from sogm_service.data import INTEL_LOG

__all__ = ["INTEL_LOG", "needs_intel", "raw_session"]

# The Intel Research Lab log ships with the package (sogm_service/data/); a wheel built without
# its package data would lack it, and then these tests say so instead of failing on a path.
needs_intel = pytest.mark.skipif(not INTEL_LOG.exists(), reason="the package data is missing")


def raw_session(endpoint: str) -> zenoh.Session:
    """A client-mode Zenoh session to ``endpoint`` built with zenoh alone (scouting off)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)
