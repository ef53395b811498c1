"""Placing an ISM against the map before it is fused (paper section III-C.2), pure.

The ISM is brought to map resolution in its own frame (matching needs one scale), the map is
sampled over the claimed footprint plus the matcher's margin
(:func:`~sogm_service.core.matching.match.match_window`), and ORB
matching (:func:`~sogm_service.core.matching.match.match_ism`)
proposes a correction.  Reading the map
is the caller's business, so this module never sees a lock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry
from sogm_service.core.matching.match import (
    MatchResult,
    corrected_geometry,
    match_ism,
    prior_matrix,
)
from sogm_service.core.matching.params import MatchParams
from sogm_service.core.resample import resample_logodds

MIN_KNOWN_CELLS = 200
"""Fewer known map cells than this around an ISM: nothing to match against yet (skipped)."""


@dataclass(frozen=True)
class Alignment:
    """The outcome of scan matching one ISM against the map."""

    result: MatchResult | None  # None: skipped (nothing in the map to match against yet)
    increments: npt.NDArray[np.int16]  # the ISM at map resolution, in its own frame
    claimed: GridGeometry  # where the ISM says it is (map resolution)
    corrected: GridGeometry | None  # where matching put it (when accepted)


def at_map_resolution(inc: npt.NDArray[np.int16], geometry: GridGeometry,
                      resolution: float) -> tuple[npt.NDArray[np.int16], GridGeometry]:
    """The ISM resampled (biodds) to ``resolution`` in its own pose, and that geometry."""
    claimed = GridGeometry(resolution,
                           max(1, round(geometry.width * geometry.resolution / resolution)),
                           max(1, round(geometry.height * geometry.resolution / resolution)),
                           geometry.origin)
    if claimed == geometry:
        return inc, claimed
    return resample_logodds(inc, geometry, claimed, "biodds"), claimed


def align(ism: npt.NDArray[np.int16], claimed: GridGeometry,
          surroundings: npt.NDArray[np.int16] | None, window: GridGeometry,
          params: MatchParams, min_known: int = MIN_KNOWN_CELLS) -> Alignment:
    """Match ``ism`` (at ``claimed``) against the map's ``surroundings`` sampled in ``window``.

    ``surroundings`` is None when the map does not have the layer yet; with fewer than
    ``min_known`` known cells matching is skipped too (``result`` None).
    """
    if surroundings is None or np.count_nonzero(surroundings) < min_known:
        return Alignment(None, ism, claimed, None)
    result = match_ism(ism, surroundings, params, prior_matrix(claimed, window))
    corrected = corrected_geometry(claimed, window, result) if result.accepted else None
    return Alignment(result, ism, claimed, corrected)
