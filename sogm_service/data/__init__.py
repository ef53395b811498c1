"""Data that ships with the package: the Intel Research Lab laser log.

``intel-corrected.log.gz`` is the corrected Intel Research Lab (Seattle) log of the Radish robotics
data set repository, in CARMEN's log format (910 front-laser scans with corrected poses): public
data, used by ``sogm-service replay carmen``'s examples, ``sogm-service eval matching`` and the
tests of the CARMEN reader, the laser model and scan matching on real scans.
"""

from __future__ import annotations

from pathlib import Path

INTEL_LOG = Path(__file__).with_name("intel-corrected.log.gz")
"""The Intel Research Lab log (gzip, CARMEN format)."""
