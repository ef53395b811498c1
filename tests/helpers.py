"""Helpers shared by unit and integration tests: the public data sets they read."""

from __future__ import annotations

import pytest

from sogm_service.data import INTEL_LOG

__all__ = ["INTEL_LOG", "needs_intel"]

# The Intel Research Lab log ships with the package (sogm_service/data/); a wheel built without
# its package data would lack it, and then these tests say so instead of failing on a path.
needs_intel = pytest.mark.skipif(not INTEL_LOG.exists(), reason="the package data is missing")
