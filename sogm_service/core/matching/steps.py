"""The steps of scan matching (:mod:`sogm_service.core.matching.match`): rendering the log-odds as
images ORB can read, features and their pairing gated by the allowed correction, RANSAC, the
ECC refinement, and the agreement score.  Pure: numpy and OpenCV, no I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from sogm_service.core import logodds
from sogm_service.core.matching.params import MatchParams

Matrix3 = npt.NDArray[np.float64]
Image = npt.NDArray[np.uint8]
Points = npt.NDArray[np.float32]

# ---------------------------------------------------------------------------------------------
# Step 1: rendering and the agreement score


def to_nats(l: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Log-odds in nats: integer arrays are fixed point (``logodds.SCALE``), floats are nats."""
    a = np.asarray(l)
    if np.issubdtype(a.dtype, np.integer):
        return logodds.from_fixed(a)
    return a.astype(np.float32, copy=False)


def render_u8(l_nats: npt.NDArray[np.float32], params: MatchParams) -> Image:
    """Log-odds -> 8-bit image keeping free, unknown and occupied distinct (III-C.2 step 1).

    Ternary by ``known_threshold``, not proportional to the evidence: an ISM and a map that
    has seen many ISMs differ in magnitude but must look alike.  Unknown sits just above free
    (not mid-grey) so that the edge of a sensor's field of view - which the map does not share
    - is weak, while occupied structure, which both share, is strong.
    """
    t = np.float32(params.known_threshold)
    img = np.full(l_nats.shape, params.unknown_level, np.uint8)
    img[l_nats >= t] = params.occupied_level
    img[l_nats <= -t] = params.free_level
    if params.blur_sigma > 0 and img.size:
        return np.asarray(cv2.GaussianBlur(img, (0, 0), params.blur_sigma), dtype=np.uint8)
    return img


def agreement(
    a_nats: npt.NDArray[np.float32], b_nats: npt.NDArray[np.float32], params: MatchParams
) -> tuple[float, int]:
    """Pearson correlation of clipped log-odds over cells known in both, and their count.

    Clipping at ``saturation`` keeps a saturated map and a mild ISM comparable; the
    correlation is NaN when fewer than ``min_overlap`` cells are known in both or one side is
    constant there (nothing to judge - e.g. an empty floor).
    """
    s = np.float32(params.saturation)
    t = params.known_threshold
    both = (np.abs(a_nats) >= t) & (np.abs(b_nats) >= t)
    n = int(np.count_nonzero(both))
    if n < params.min_overlap:
        return math.nan, n
    # Masked dense arithmetic (no fancy indexing) and float32 BLAS dots: this runs three
    # times per match on the whole window.
    x = np.where(both, np.clip(a_nats, -s, s), np.float32(0.0)).ravel()
    y = np.where(both, np.clip(b_nats, -s, s), np.float32(0.0)).ravel()
    m = both.ravel().astype(np.float32)
    x -= np.float32(float(x.sum(dtype=np.float64)) / n) * m
    y -= np.float32(float(y.sum(dtype=np.float64)) / n) * m
    den = math.sqrt(float(np.dot(x, x)) * float(np.dot(y, y)))
    if den <= 1e-9 * n:
        return math.nan, n
    return float(np.dot(x, y)) / den, n


def warp_into(
    l_nats: npt.NDArray[np.float32], matrix: Matrix3, shape: tuple[int, int]
) -> npt.NDArray[np.float32]:
    """Resample ISM log-odds into a window of ``shape`` via ISM cells -> window cells ``matrix``.

    Bilinear on log-odds (the paper's biodds, III-C.1); outside the ISM is unknown (0).
    """
    h, w = shape
    if abs(matrix[2, 0]) + abs(matrix[2, 1]) < 1e-12 and abs(matrix[2, 2] - 1.0) < 1e-12:
        out = cv2.warpAffine(l_nats, matrix[:2], (w, h), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    else:
        out = cv2.warpPerspective(l_nats, matrix, (w, h), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return np.asarray(out, dtype=np.float32)


# ---------------------------------------------------------------------------------------------
# Steps 2 and 3: ORB features and guided matching


@dataclass(frozen=True, slots=True)
class _Features:
    points: Points  # (N, 2) continuous cell coordinates (u, v)
    descriptors: npt.NDArray[np.uint8]  # (N, 32)

    @property
    def count(self) -> int:
        return int(self.points.shape[0])


def detect(img: Image, params: MatchParams) -> _Features:
    """ORB keypoints and descriptors of a rendered grid (III-C.2: "ORB feature extraction")."""
    if img.size == 0:
        return _Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
    pad = params.patch_size
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    orb = cv2.ORB.create(
        nfeatures=params.n_features, scaleFactor=params.scale_factor, nlevels=params.n_levels,
        edgeThreshold=params.patch_size, patchSize=params.patch_size,
        fastThreshold=params.fast_threshold, scoreType=cv2.ORB_HARRIS_SCORE,
    )
    kps = orb.detect(padded, None)
    if params.upright:
        # The window is resampled in the claimed ISM frame, so the residual rotation is small;
        # ORB's intensity-centroid angle differs between a partial view and the map.
        kps = [cv2.KeyPoint(kp.pt[0], kp.pt[1], kp.size, 0.0, kp.response, kp.octave)
               for kp in kps]
    kps, desc = orb.compute(padded, kps)
    if desc is None or len(kps) == 0:
        return _Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
    pts = np.array([kp.pt for kp in kps], dtype=np.float32) - np.float32(pad)
    # Keypoints found only in the replicated padding describe no real cell.
    h, w = img.shape
    inside = (pts[:, 0] > -0.5) & (pts[:, 1] > -0.5) & (pts[:, 0] < w - 0.5) & (
        pts[:, 1] < h - 0.5)
    return _Features(pts[inside], desc[inside])


def apply(matrix: Matrix3, pts: npt.NDArray) -> npt.NDArray[np.float64]:
    """Map ``(N, 2)`` points through a 3x3 (affine or projective) transform."""
    p = np.asarray(pts, dtype=np.float64)
    q = p @ matrix[:2, :2].T + matrix[:2, 2]
    wz = p @ matrix[2, :2] + matrix[2, 2]
    return q / wz[:, None]


def gate_mask(
    ism: _Features, win: _Features, prior: Matrix3, centre: npt.NDArray[np.float64],
    params: MatchParams,
) -> npt.NDArray[np.uint8]:
    """Candidate pairs: window keypoints within reach of an acceptable correction.

    ``centre`` is the ISM's centre in ISM cells; a point at distance ``r`` from it moves by at
    most ``max_translation + 2 r sin(max_rotation / 2) + r * max_scale_change``.
    """
    q = apply(prior, ism.points)
    r = np.hypot(*(ism.points.astype(np.float64) - centre).T)
    reach = (params.max_translation + params.gate_slack
             + r * (2.0 * math.sin(0.5 * params.max_rotation) + params.max_scale_change))
    w = win.points.astype(np.float64)
    # |q - w|^2 by expansion: no (n, m, 2) temporary.
    d2 = (q * q).sum(axis=1)[:, None] + (w * w).sum(axis=1)[None, :] - 2.0 * (q @ w.T)
    return (d2 <= (reach ** 2)[:, None]).astype(np.uint8)


def match_pairs(
    ism: _Features, win: _Features, mask: npt.NDArray[np.uint8], params: MatchParams
) -> tuple[Points, Points]:
    """Hamming matching among gated candidates: ratio test, then optional cross check."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(ism.descriptors, win.descriptors, k=2, mask=mask)
    fwd: dict[int, int] = {}
    for cand in knn:
        if not cand:
            continue
        # A unique candidate within the gate passes the ratio test by definition.
        if len(cand) == 1 or cand[0].distance < params.ratio * cand[1].distance:
            fwd[cand[0].queryIdx] = cand[0].trainIdx
    if params.cross_check and fwd:
        back = bf.knnMatch(win.descriptors, ism.descriptors, k=1, mask=np.ascontiguousarray(
            mask.T))
        best = {c[0].queryIdx: c[0].trainIdx for c in back if c}
        fwd = {i: j for i, j in fwd.items() if best.get(j) == i}
    idx = np.array(sorted(fwd.items()), dtype=np.int64).reshape(-1, 2)
    return ism.points[idx[:, 0]], win.points[idx[:, 1]]


# ---------------------------------------------------------------------------------------------
# Step 4: robust estimation and the correction


def estimate(src: Points, dst: Points, params: MatchParams) -> tuple[Matrix3 | None, int]:
    """RANSAC model ISM cells -> window cells and its inlier count (seeded, deterministic)."""
    cv2.setRNGSeed(params.seed)
    if params.model == "homography":
        h, inl = cv2.findHomography(src, dst, cv2.RANSAC, params.ransac_threshold,
                                    maxIters=params.ransac_max_iters,
                                    confidence=params.ransac_confidence)
        m = None if h is None else np.asarray(h, dtype=np.float64)
    else:
        a, inl = cv2.estimateAffinePartial2D(
            src, dst, method=cv2.RANSAC, ransacReprojThreshold=params.ransac_threshold,
            maxIters=params.ransac_max_iters, confidence=params.ransac_confidence,
            refineIters=10)
        m = None if a is None else np.vstack([np.asarray(a, dtype=np.float64), [0.0, 0.0, 1.0]])
    if m is None or not np.all(np.isfinite(m)) or inl is None:
        return None, 0
    return m, int(np.count_nonzero(inl))


def refine_ecc(
    ism_img: Image, ism_known: npt.NDArray[np.bool_], win_img: Image, matrix: Matrix3,
    params: MatchParams,
) -> Matrix3 | None:
    """Sub-cell rigid refinement of a RANSAC model by ECC (enhanced correlation coefficient).

    ORB keypoints sit on a (pyramid) pixel lattice and a partial view yields few inliers, so
    the feature estimate alone is good to a cell or two; ECC aligns the rendered images
    directly, coarse to fine.  The window is the template and the ISM the input, so the ISM's
    known mask can be passed as ECC's input mask: the ISM's unknown cells never count.
    ``None`` when ECC fails to converge.
    """
    # ECC works on the window block under the ISM's known cells only (the rest cannot count).
    x0, y0, tmpl = _ecc_template(win_img, ism_known, matrix, params)
    crop = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    to_crop = np.linalg.inv(crop) @ _rigid_about_centre(matrix, ism_img.shape)
    inp, known = ism_img, ism_known
    if abs(math.atan2(to_crop[1, 0], to_crop[0, 0])) > math.radians(60.0):
        # OpenCV's Euclidean ECC reads its angle back with asin, so it cannot hold rotations
        # beyond 90 degrees: pre-warp the ISM into the crop and solve for the residual only.
        # (Not always: the extra interpolation costs accuracy, ~0.1 cell on partial views.)
        size = (tmpl.shape[1], tmpl.shape[0])
        inp = np.asarray(cv2.warpAffine(ism_img, to_crop[:2], size, flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT,
                                        borderValue=params.unknown_level), dtype=np.uint8)
        known = np.asarray(cv2.warpAffine(ism_known.astype(np.uint8), to_crop[:2], size,
                                          flags=cv2.INTER_NEAREST), dtype=bool)
        pre = to_crop
    else:
        pre = np.eye(3)
    w = np.linalg.inv(to_crop) @ pre  # crop cells -> input cells
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.refine_iters, 1e-4)
    try:
        for level, ksize in params.refine_stages:
            w = _ecc_stage(tmpl, inp, known, w, level, ksize, crit)
    except cv2.error:
        return None
    # ISM -> input -> crop -> window.
    return np.asarray(crop @ np.linalg.inv(w) @ pre, dtype=np.float64)


def _ecc_template(
    win_img: Image, ism_known: npt.NDArray[np.bool_], matrix: Matrix3, params: MatchParams
) -> tuple[int, int, Image]:
    """The window block around the ISM's known cells placed by ``matrix``, and its corner."""
    h, w = win_img.shape
    vs, us = np.nonzero(ism_known)
    if len(us) == 0:
        return 0, 0, win_img
    pts = np.array([[us.min(), vs.min()], [us.max(), vs.min()], [us.max(), vs.max()],
                    [us.min(), vs.max()]], dtype=np.float64)
    pad = params.refine_max_shift + 2 * max(k for _, k in params.refine_stages)
    q = apply(matrix, pts)
    x0 = int(max(0, math.floor(q[:, 0].min() - pad)))
    y0 = int(max(0, math.floor(q[:, 1].min() - pad)))
    x1 = int(min(w, math.ceil(q[:, 0].max() + pad) + 1))
    y1 = int(min(h, math.ceil(q[:, 1].max() + pad) + 1))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return 0, 0, win_img
    return x0, y0, win_img[y0:y1, x0:x1]


def _ecc_stage(
    tmpl: Image, ism_img: Image, ism_known: npt.NDArray[np.bool_], w: Matrix3, level: int,
    ksize: int, crit: tuple[int, int, float],
) -> Matrix3:
    """One ECC stage on images reduced ``2**level`` times (pyrDown keeps x_half = x / 2)."""
    t, i = tmpl.astype(np.float32), ism_img.astype(np.float32)
    m = ism_known.astype(np.uint8)
    for _ in range(level):
        t = np.asarray(cv2.pyrDown(t), dtype=np.float32)
        i = np.asarray(cv2.pyrDown(i), dtype=np.float32)
        m = m[::2, ::2]
    f = float(2 ** level)
    scale = np.diag([1.0 / f, 1.0 / f, 1.0])
    wl = (scale @ w @ np.linalg.inv(scale))[:2].astype(np.float32)
    _, found = cv2.findTransformECC(t, i, wl,
                                    cv2.MOTION_EUCLIDEAN, crit, np.ascontiguousarray(m), ksize)
    full = np.vstack([np.asarray(found, dtype=np.float64), [0.0, 0.0, 1.0]])
    return np.asarray(np.linalg.inv(scale) @ full @ scale, dtype=np.float64)


def _rigid_about_centre(matrix: Matrix3, shape: tuple[int, int]) -> Matrix3:
    """The rigid part of a similarity, keeping where the ISM's centre lands."""
    c = ism_centre(shape)
    theta = math.atan2(matrix[1, 0], matrix[0, 0])
    cs, sn = math.cos(theta), math.sin(theta)
    target = apply(matrix, c[None])[0]
    t = target - np.array([cs * c[0] - sn * c[1], sn * c[0] + cs * c[1]])
    return np.array([[cs, -sn, t[0]], [sn, cs, t[1]], [0.0, 0.0, 1.0]])


def fit_similarity(src: npt.NDArray, dst: npt.NDArray) -> Matrix3:
    """Least-squares similarity (rotation, uniform scale, translation) ``src -> dst`` (Umeyama).

    Used to read rotation and scale off a homography and to drop its projective part.
    """
    s = np.asarray(src, dtype=np.float64)
    d = np.asarray(dst, dtype=np.float64)
    ms, md = s.mean(axis=0), d.mean(axis=0)
    s0, d0 = s - ms, d - md
    # For 2-D similarities the least-squares solution is closed-form in complex numbers.
    zs = s0[:, 0] + 1j * s0[:, 1]
    zd = d0[:, 0] + 1j * d0[:, 1]
    k = complex(np.vdot(zs, zd) / max(float(np.vdot(zs, zs).real), 1e-12))
    a, b = k.real, k.imag
    t = md - np.array([a * ms[0] - b * ms[1], b * ms[0] + a * ms[1]])
    return np.array([[a, -b, t[0]], [b, a, t[1]], [0.0, 0.0, 1.0]])


def ism_centre(shape: tuple[int, int]) -> npt.NDArray[np.float64]:
    """Continuous cell coordinates ``(u, v)`` of a grid's centre."""
    return np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])


def ism_corners(shape: tuple[int, int]) -> npt.NDArray[np.float64]:
    """The four outer corners of a grid in continuous cell coordinates."""
    h, w = shape
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
