"""Helpers shared by unit and integration tests: where the public data sets they read are."""

from __future__ import annotations

from pathlib import Path

import pytest

from sogm_service.eval.matching import INTEL_LOG as _EVAL_DEFAULT

ROOT = Path(__file__).resolve().parents[1]

# The Intel Research Lab log (public CARMEN data, not part of the repository): in the same data
# folder beside this checkout (as in CI), else where ``sogm-service eval matching`` reads it by
# default.
_BESIDE = ROOT.parent / _EVAL_DEFAULT.relative_to(_EVAL_DEFAULT.parents[3])
INTEL_LOG = next((p for p in (_BESIDE, _EVAL_DEFAULT) if p.exists()), _EVAL_DEFAULT)
needs_intel = pytest.mark.skipif(not INTEL_LOG.exists(), reason="the Intel log is not available")
