"""Scan matching of misaligned ISMs against the map (paper section III-C.2).

Robots with drifting odometry send ISMs that are offset and rotated against the map; fusing them
blindly smears walls.  The paper recovers the missing transform "by utilizing ORB feature
extraction of the ISM and the corresponding SOGM's surrounding"; the features "are matched via
the distance of pairwise feature candidates which again leads to a homography" (III-C.2, Fig. 4).

Pipeline of :func:`match_ism` (all in cell units, the ISM already resampled to map resolution):

1. *Render* both grids to 8-bit images (:func:`render_u8`): ternary by ``known_threshold`` -
   free black, unknown dark grey, occupied white - so occupied, free and unknown stay distinct,
   an ISM's mild log-odds and the map's saturated ones look alike, and the edge of a sensor's
   field of view (free against unknown, absent from the map) is weak while the walls both
   share are strong.  A light Gaussian blur steadies FAST/BRIEF on these binary images.
2. *Detect* ORB keypoints in both (OpenCV), the images padded by replication so that keypoints
   near the border survive without the padding inventing edges.  **Upright, one level**: the
   window is resampled in the claimed ISM frame at the ISM's resolution, so the residual
   rotation is small (<= ``max_rotation``) and the scale is 1; ORB's intensity-centroid angle
   differs between a partial laser view and the map (measured: the true correspondence was the
   best gated candidate for 11% of keypoints with ORB angles, 45% upright and single-level).
3. *Match* Hamming descriptors, **guided by the claimed pose**: a pair is only a candidate when
   the window keypoint lies where the ISM keypoint could land under the largest correction that
   would be accepted anyway (``gate_mask``).  This removes most of the repetitive-structure
   outliers of grid maps.  Then mutual best matches (cross check); Lowe's ratio test is
   available (``ratio < 1``) but off by default - within the gate, similar-looking wall corners
   are legitimate neighbours, and the test threw away more true matches than false ones.
4. *Estimate* the transform robustly with RANSAC (``cv2.setRNGSeed`` first, so it is
   deterministic): ``cv2.estimateAffinePartial2D`` (rotation, translation, uniform scale - the
   physically right model for two 2-D grids of the same resolution; default) or the paper's
   full homography (``cv2.findHomography``, ``model="homography"``).
5. *Refine* (partial-affine model only): ORB keypoints sit on the pixel lattice and a partial
   view yields few inliers, which leaves the estimate a cell or two off; ECC
   (``cv2.findTransformECC``, Euclidean, coarse to fine, masked by the ISM's known cells)
   aligns the rendered images to sub-cell precision.  The refined model is kept only if it
   stays near the RANSAC one and agrees better with the map.
6. *Accept* only if enough inliers support it, the correction is within bounds, the scale is ~1
   (and a homography is nearly a similarity) and the agreement of the corrected ISM with the
   map (:func:`agreement`: Pearson correlation of clipped log-odds over cells known in both) is
   at least ``min_score`` and not worse than under the claimed pose.  Every failure carries a
   :class:`MatchReason`; a featureless ISM (empty floor) fails with ``too_few_features`` or at
   the quality check, never with a random correction.

Conventions.  The ISM and window arrays are indexed ``[v, u]`` like every grid here
(:mod:`sogm_service.core.geometry`); continuous cell coordinates put cell centres on integers.
``prior`` is the 3x3 map ISM cell -> window cell implied by the claimed pose
(:func:`prior_matrix`); ``MatchResult.matrix`` is the estimated map ISM cell -> window cell.
The *correction* ``C = matrix @ inv(prior)`` acts in window cells; it is reported as the
displacement ``(dx, dy)`` of the ISM's centre, the rotation ``dtheta`` (rad, counter-clockwise
in the grid's ``u, v`` axes = the map frame's x, y axes when the window is axis-aligned) and the
scale about that centre.  :func:`corrected_geometry` turns it into the ISM's corrected
:class:`~sogm_service.core.geometry.GridGeometry` so the server simply resamples the ISM with it.

Log-odds inputs: integer arrays are the fixed point of :mod:`sogm_service.core.logodds`
(``1 / SCALE`` nat), floating arrays are nats.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.matching.params import MatchParams, MatchReason
from sogm_service.core.matching.steps import (
    Image,
    Matrix3,
    agreement,
    apply,
    detect,
    estimate,
    fit_similarity,
    gate_mask,
    ism_centre,
    ism_corners,
    match_pairs,
    refine_ecc,
    render_u8,
    to_nats,
    warp_into,
)


@dataclass(frozen=True, slots=True)
class Correction:
    """The correction about the ISM's centre, in window cells: shift, rotation (rad), scale."""

    dx: float
    dy: float
    dtheta: float
    scale: float

    @property
    def translation(self) -> float:
        return math.hypot(self.dx, self.dy)


@dataclass(frozen=True, slots=True)
class MatchResult:
    """Outcome of :func:`match_ism`.

    ``matrix`` (3x3, ISM cells -> window cells) and ``correction`` are filled whenever RANSAC
    found a model, also when it was then refused - a report-only mode can publish them.
    """

    accepted: bool
    reason: MatchReason
    correction: Correction | None
    matrix: Matrix3 | None
    prior: Matrix3
    n_features_ism: int
    n_features_map: int
    n_matches: int
    inliers: int
    score_before: float
    score_after: float
    elapsed_s: float
    details: dict[str, float] = field(default_factory=dict)

    @property
    def affine(self) -> npt.NDArray[np.float64] | None:
        """The top 2x3 of :attr:`matrix` (exact for the partial-affine model)."""
        return None if self.matrix is None else self.matrix[:2]

    def summary(self) -> dict[str, object]:
        """JSON-ready fields (plain floats and lists) for stats and a report-only publisher."""
        c = self.correction
        return {
            "accepted": self.accepted, "reason": self.reason.value,
            "correction": None if c is None else {
                "dx": c.dx, "dy": c.dy, "dtheta": c.dtheta, "scale": c.scale},
            "matrix": None if self.matrix is None else self.matrix.tolist(),
            "n_features_ism": self.n_features_ism, "n_features_map": self.n_features_map,
            "n_matches": self.n_matches, "inliers": self.inliers,
            "score_before": _finite_or_none(self.score_before),
            "score_after": _finite_or_none(self.score_after),
            "elapsed_s": self.elapsed_s, **self.details,
        }


def _finite_or_none(x: float) -> float | None:
    """NaN (no score) as ``None``: JSON and msgpack consumers need no NaN handling."""
    return x if math.isfinite(x) else None


def correction_of(
    matrix: Matrix3, prior: Matrix3, shape: tuple[int, int]
) -> tuple[Correction, float]:
    """The correction about the ISM centre and, for a homography, its distortion in cells.

    The distortion is how far the model moves the ISM's corners away from the nearest
    similarity - 0 for the partial-affine model.
    """
    pts = np.vstack([ism_corners(shape), ism_centre(shape)])
    claimed = apply(prior, pts)
    found = apply(matrix, pts)
    sim = fit_similarity(claimed, found)
    distortion = float(np.max(np.hypot(*(apply(sim, claimed) - found).T)))
    c = claimed[-1]
    shift = found[-1] - c
    theta = math.atan2(sim[1, 0], sim[0, 0])
    scale = math.hypot(sim[0, 0], sim[1, 0])
    return Correction(float(shift[0]), float(shift[1]), theta, scale), distortion


# ---------------------------------------------------------------------------------------------
# Step 5 and the public entry point


def default_prior(ism_shape: tuple[int, int], window_shape: tuple[int, int]) -> Matrix3:
    """ISM cells -> window cells when the ISM is centred, axis-aligned, in the window."""
    off = ism_centre(window_shape) - ism_centre(ism_shape)
    return np.array([[1.0, 0.0, off[0]], [0.0, 1.0, off[1]], [0.0, 0.0, 1.0]])


def prior_matrix(ism_geom: GridGeometry, window_geom: GridGeometry) -> Matrix3:
    """ISM cells -> window cells implied by the two geometries (the claimed pose)."""
    return np.asarray(window_geom.world_to_cell() @ ism_geom.cell_to_world(), dtype=np.float64)


def match_window(ism_geom: GridGeometry, params: MatchParams) -> GridGeometry:
    """The map window to resample for matching: the claimed ISM grown by the window margin.

    Same resolution and yaw as the ISM, so :func:`prior_matrix` is a pure shift (and equal to
    :func:`default_prior`).
    """
    m = params.window_margin(ism_geom.width, ism_geom.height)
    return ism_geom.subgrid(-m, -m, ism_geom.width + 2 * m, ism_geom.height + 2 * m)


def check_correction(
    corr: Correction, distortion: float, inliers: int, params: MatchParams
) -> MatchReason | None:
    """Acceptance rules that need no map cells; ``None`` when they all pass."""
    if inliers < params.min_inliers:
        return MatchReason.TOO_FEW_INLIERS
    if distortion > params.max_distortion or abs(corr.scale - 1.0) > params.max_scale_change:
        return MatchReason.DEGENERATE
    if corr.translation > params.max_translation or abs(corr.dtheta) > params.max_rotation:
        return MatchReason.CORRECTION_TOO_LARGE
    return None


def _score(
    ism: npt.NDArray[np.float32], win: npt.NDArray[np.float32], matrix: Matrix3,
    params: MatchParams,
) -> tuple[float, int]:
    """Agreement of the ISM placed by ``matrix`` with the window, and the overlap."""
    return agreement(warp_into(ism, matrix, win.shape), win, params)


def _verdict(before: float, after: float, n_after: int, params: MatchParams) -> MatchReason:
    """The quality check: the corrected ISM must agree with the map, and better than before."""
    if n_after < params.min_overlap:
        return MatchReason.TOO_LITTLE_OVERLAP
    # NaN compares False: an undefined score (constant cells) never counts as agreement.
    if not after >= params.min_score:
        return MatchReason.POOR_AGREEMENT
    if not math.isnan(before) and not after >= before + params.min_gain:
        return MatchReason.NO_IMPROVEMENT
    return MatchReason.OK


def _refined(
    m: Matrix3, imgs: tuple[Image, Image], ism: npt.NDArray[np.float32],
    win: npt.NDArray[np.float32], params: MatchParams,
) -> tuple[Matrix3, float, int, bool]:
    """The better of the RANSAC model and its ECC refinement, by agreement with the map.

    Returns the matrix, its score and overlap, and whether the refinement was taken.
    """
    score, n = _score(ism, win, m, params)
    if not params.refine or params.model != "partial_affine":
        return m, score, n, False
    known = np.abs(ism) >= params.known_threshold
    r = refine_ecc(imgs[0], known, imgs[1], m, params)
    if r is None:
        return m, score, n, False
    c = ism_centre(ism.shape)[None]
    if float(np.hypot(*(apply(r, c) - apply(m, c))[0])) > params.refine_max_shift:
        return m, score, n, False  # ECC wandered off to another optimum
    score_r, n_r = _score(ism, win, r, params)
    if score_r > score or math.isnan(score):
        return r, score_r, n_r, True
    return m, score, n, False


def match_ism(
    ism_logodds: npt.ArrayLike,
    map_window_logodds: npt.ArrayLike,
    params: MatchParams | None = None,
    prior: Matrix3 | None = None,
) -> MatchResult:
    """Recover the transform of a misaligned ISM against the map window (paper III-C.2).

    ``ism_logodds`` (``h x w``) and ``map_window_logodds`` (``H x W``) share one resolution;
    ``prior`` maps ISM cells to window cells under the claimed pose (default: centred,
    axis-aligned - what :func:`match_window` produces).  Resample the window with
    :func:`match_window` (the ISM's own frame): any other window works too (give its
    :func:`prior_matrix`), but then descriptors must be rotation-invariant, which is weaker.
    The window must extend ``params.window_margin`` beyond the ISM or large corrections fall
    off its edge.  Raises ``ValueError`` only for non-2-D arrays; never on content: every
    failure is a refused result with its :class:`MatchReason`.
    """
    t0 = time.perf_counter()
    p = params or MatchParams()
    ism = to_nats(ism_logodds)
    win = to_nats(map_window_logodds)
    if ism.ndim != 2 or win.ndim != 2:
        raise ValueError("ISM and map window must be 2-D grids")
    pr = default_prior(ism.shape, win.shape) if prior is None else np.asarray(prior, np.float64)
    if p.upright and abs(math.atan2(pr[1, 0], pr[0, 0])) > p.max_rotation:
        # The window is not in the ISM's frame (not from match_window): upright descriptors
        # would face a large rotation, so let ORB orient them.
        p = replace(p, upright=False)
    imgs = (render_u8(ism, p), render_u8(win, p))
    f_ism = detect(imgs[0], p)
    f_win = detect(imgs[1], p)

    def done(reason: MatchReason, **kw: object) -> MatchResult:
        fields: dict[str, object] = {
            "correction": None, "matrix": None, "n_matches": 0, "inliers": 0,
            "score_before": math.nan, "score_after": math.nan} | kw
        return MatchResult(accepted=reason is MatchReason.OK, reason=reason, prior=pr,
                           n_features_ism=f_ism.count, n_features_map=f_win.count,
                           elapsed_s=time.perf_counter() - t0, **fields)  # type: ignore[arg-type]

    if min(f_ism.count, f_win.count) < p.min_features:
        return done(MatchReason.TOO_FEW_FEATURES)
    mask = gate_mask(f_ism, f_win, pr, ism_centre(ism.shape), p)
    src, dst = match_pairs(f_ism, f_win, mask, p)
    if len(src) < max(p.min_inliers, 4):
        return done(MatchReason.TOO_FEW_MATCHES, n_matches=len(src))
    m, inliers = estimate(src, dst, p)
    if m is None:
        return done(MatchReason.NO_TRANSFORM, n_matches=len(src))
    if inliers < p.min_inliers:
        return done(MatchReason.TOO_FEW_INLIERS, matrix=m, n_matches=len(src), inliers=inliers,
                    correction=correction_of(m, pr, ism.shape)[0])
    m, after, n_after, refined = _refined(m, imgs, ism, win, p)
    corr, distortion = correction_of(m, pr, ism.shape)
    found = {"correction": corr, "matrix": m, "n_matches": len(src), "inliers": inliers,
             "score_after": after, "details": {"refined": float(refined)}}
    refused = check_correction(corr, distortion, inliers, p)
    if refused is not None:
        return done(refused, **found)
    before, _ = _score(ism, win, pr, p)
    return done(_verdict(before, after, n_after, p), score_before=before, **found)


def corrected_geometry(
    ism_geom: GridGeometry, window_geom: GridGeometry, result: MatchResult,
    keep_scale: bool = False,
) -> GridGeometry:
    """The ISM's geometry in the map frame with the match's correction applied.

    ``result.matrix`` maps ISM cells to window cells, so ``window.cell_to_world @ matrix`` is
    the corrected ISM cell -> world map.  A homography is replaced by its nearest similarity
    (a grid geometry cannot hold perspective).  Unless ``keep_scale``, the scale is dropped and
    the rotation applied about the ISM's centre, whose corrected position is kept: a sensor's
    metric ISM has no scale error, a fitted ~1.0 scale is noise.
    """
    if result.matrix is None:
        raise ValueError(f"match has no transform to apply (reason: {result.reason})")
    shape = ism_geom.shape
    pts = np.vstack([ism_corners(shape), ism_centre(shape)])
    a = window_geom.cell_to_world() @ fit_similarity(pts, apply(result.matrix, pts))
    # ``a`` maps ISM cells to metres, so its scale is the corrected resolution itself.
    res = math.hypot(a[0, 0], a[1, 0]) if keep_scale else ism_geom.resolution
    yaw = math.atan2(a[1, 0], a[0, 0])
    # Keep the corrected centre; rebuild the corner (origin) from it with the chosen resolution.
    centre_world = apply(a, ism_centre(shape)[None])[0]
    half = Pose2D(0.0, 0.0, yaw).transform_points(
        np.array([shape[1] * res / 2.0, shape[0] * res / 2.0]))
    origin = Pose2D(float(centre_world[0] - half[0]), float(centre_world[1] - half[1]), yaw)
    return GridGeometry(res, ism_geom.width, ism_geom.height, origin)
