"""The tuning of scan matching and the reasons a match is accepted or refused: what the pipeline
(:mod:`sogm_service.core.matching.match`) and its steps (:mod:`sogm_service.core.matching.steps`)
both read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

Model = Literal["partial_affine", "homography"]


class MatchReason(StrEnum):
    """Why a match was accepted or refused (machine-readable, counted by the server)."""

    OK = "ok"
    TOO_FEW_FEATURES = "too_few_features"  # ORB found too little structure in ISM or window
    TOO_FEW_MATCHES = "too_few_matches"  # descriptor matching left too few candidate pairs
    NO_TRANSFORM = "no_transform"  # RANSAC found no model
    TOO_FEW_INLIERS = "too_few_inliers"
    DEGENERATE = "degenerate_transform"  # mirror, strong perspective or scale far from 1
    CORRECTION_TOO_LARGE = "correction_too_large"
    TOO_LITTLE_OVERLAP = "too_little_overlap"  # too few cells known in both to judge quality
    NO_IMPROVEMENT = "no_improvement"  # corrected ISM agrees less with the map than before
    POOR_AGREEMENT = "poor_agreement"  # corrected ISM still agrees poorly with the map


@dataclass(frozen=True, slots=True)
class MatchParams:
    """Tuning of :func:`match_ism`; lengths are in cells, angles in radians, log-odds in nats."""

    model: Model = "partial_affine"
    # Rendering (step 1)
    saturation: float = 2.0  # |l| clip of the agreement score
    known_threshold: float = 0.3  # |l| below this counts as unknown
    free_level: int = 0
    unknown_level: int = 40
    occupied_level: int = 255
    blur_sigma: float = 1.0  # ORB is noisy on binary images; a light blur steadies it
    # ORB (step 2)
    n_features: int = 800
    scale_factor: float = 1.3
    n_levels: int = 1  # same resolution on both sides: scale levels only add confusion
    patch_size: int = 23
    fast_threshold: int = 12
    upright: bool = True  # descriptors at angle 0 (no orientation invariance needed, see detect)
    # Matching (step 3)
    ratio: float = 1.0  # Lowe's ratio test among gated candidates; 1.0 (default) disables it
    cross_check: bool = True  # keep only mutual best matches
    gate_slack: float = 4.0  # extra cells on top of the correction bounds
    # RANSAC (step 4)
    ransac_threshold: float = 2.0
    ransac_max_iters: int = 2000
    ransac_confidence: float = 0.995
    seed: int = 0
    # ECC refinement (partial-affine model only)
    refine: bool = True
    refine_iters: int = 50
    # (pyramid level, Gaussian kernel) per ECC stage, coarse to fine
    refine_stages: tuple[tuple[int, int], ...] = ((1, 5), (0, 5))
    refine_max_shift: float = 6.0  # cells ECC may move the ISM centre away from RANSAC
    # Acceptance (step 5)
    min_features: int = 20
    min_inliers: int = 6
    max_translation: float = 20.0
    max_rotation: float = math.radians(15.0)
    max_scale_change: float = 0.05  # |scale - 1|
    max_distortion: float = 2.0  # homography only: cells off the nearest similarity at corners
    min_overlap: int = 200  # cells known in both needed for the quality check
    min_gain: float = 0.0  # score_after must be >= score_before + min_gain
    min_score: float = 0.3  # and >= this
    # Window (step 0): cells of map beyond the reach of the largest accepted correction, so
    # that map keypoints near that reach are described from real cells (``[ism.matching]
    # margin_m`` of the service config).
    window_extra: float = 0.0

    def __post_init__(self) -> None:
        if self.model not in ("partial_affine", "homography"):
            raise ValueError(f"model must be 'partial_affine' or 'homography', got {self.model!r}")
        if any(k < 1 or k % 2 == 0 or lvl < 0 for lvl, k in self.refine_stages):
            raise ValueError("refine_stages need levels >= 0 and odd Gaussian kernels")
        if not (0 < self.ratio <= 1.0):
            raise ValueError(f"ratio must lie in (0, 1], got {self.ratio}")
        if self.min_inliers < 4 or self.min_features < 4:
            raise ValueError("min_inliers and min_features must be at least 4")
        if not (self.free_level < self.unknown_level < self.occupied_level <= 255
                and self.free_level >= 0):
            raise ValueError("need 0 <= free_level < unknown_level < occupied_level <= 255")
        if self.saturation <= 0 or self.known_threshold < 0:
            raise ValueError("saturation must be > 0 and known_threshold >= 0")
        if not (math.isfinite(self.window_extra) and self.window_extra >= 0):
            raise ValueError(f"window_extra must be >= 0, got {self.window_extra}")

    def window_margin(self, ism_width: int, ism_height: int) -> int:
        """Cells of map to add around the claimed ISM so any acceptable correction stays inside.

        A rotation by ``max_rotation`` about the ISM's centre moves its corners by
        ``2 r sin(max_rotation / 2)`` with ``r`` the half diagonal.
        """
        r = 0.5 * math.hypot(ism_width, ism_height)
        swing = 2.0 * r * math.sin(0.5 * self.max_rotation)
        return math.ceil(self.max_translation + swing + self.gate_slack + self.window_extra)
