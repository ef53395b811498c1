"""Scan matching of misaligned ISMs (paper III-C.2): synthetic recovery, refusals, geometry.

Every synthetic case is seeded.  An ISM is cut from a synthetic floor plan at a *true* pose; the
robot *claims* a pose shifted by up to 10 cells and rotated by up to 10 degrees; the map window
is resampled around the claimed pose.  A match passes when the corrected ISM geometry puts the
ISM's centre within 1 cell of the truth and its heading within 1 degree.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sogm_service.adapters.carmen import LaserScan, read_carmen
from sogm_service.adapters.laser import laser_ism
from sogm_service.bench.matching import benchmark_match, synthetic_floorplan
from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.matching import match as mt
from sogm_service.core.matching import params as mp
from sogm_service.core.resample import resample_logodds
from tests.helpers import INTEL_LOG, needs_intel

RES = 0.05
PLAN = 640
ISM = 160
N_CASES = 40


@dataclass(frozen=True)
class Case:
    ism: npt.NDArray[np.int16]
    truth: GridGeometry
    claimed: GridGeometry
    window_geom: GridGeometry
    window: npt.NDArray[np.int16]

    def match(self, params: mp.MatchParams) -> mt.MatchResult:
        return mt.match_ism(self.ism, self.window, params,
                            mt.prior_matrix(self.claimed, self.window_geom))

    def errors(self, geom: GridGeometry) -> tuple[float, float]:
        """(centre error in cells, heading error in degrees) of ``geom`` against the truth."""
        return centre_error(geom, self.truth), heading_error(geom, self.truth)


def centre(g: GridGeometry) -> npt.NDArray[np.float64]:
    return (g.cell_to_world() @ np.array([(g.width - 1) / 2, (g.height - 1) / 2, 1.0]))[:2]


def centre_error(a: GridGeometry, b: GridGeometry) -> float:
    return float(np.hypot(*(centre(a) - centre(b)))) / RES


def heading_error(a: GridGeometry, b: GridGeometry) -> float:
    d = (a.origin.yaw - b.origin.yaw + math.pi) % (2 * math.pi) - math.pi
    return abs(math.degrees(d))


def grid_at(cx: float, cy: float, yaw: float, n: int = ISM) -> GridGeometry:
    """An ``n x n`` ISM geometry whose centre is at plan cell ``(cx, cy)`` with heading ``yaw``."""
    corner = Pose2D(cx * RES, cy * RES, yaw).compose(Pose2D(-n * RES / 2, -n * RES / 2, 0.0))
    return GridGeometry(RES, n, n, corner)


def laser_view(full: npt.NDArray[np.int16], rng: np.random.Generator,
               beams: int = 540, noise: float = 0.005) -> npt.NDArray[np.int16]:
    """What a 360-degree laser at the ISM's centre sees of ``full``: free up to the first
    occupied cell, that cell occupied, the rest unknown; mild ISM log-odds and a little noise."""
    n = full.shape[0]
    c = (n - 1) / 2
    ang = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    steps = np.arange(0.0, n * 0.71, 0.5)
    iu = np.rint(c + np.cos(ang)[:, None] * steps).astype(np.int64)
    iv = np.rint(c + np.sin(ang)[:, None] * steps).astype(np.int64)
    inside = (iu >= 0) & (iv >= 0) & (iu < n) & (iv < n)
    occ = np.zeros(inside.shape, bool)
    occ[inside] = full[iv[inside], iu[inside]] > 0
    first = np.where(occ.any(axis=1), occ.argmax(axis=1), len(steps))[:, None]
    k = np.arange(len(steps))[None, :]
    out = np.zeros((n, n), np.float32)
    free, hit = inside & (k < first), inside & (k == first)
    out[iv[free], iu[free]] = -0.85  # P = 0.3
    out[iv[hit], iu[hit]] = 1.4  # P = 0.8
    flip = (rng.random((n, n)) < noise) & (out != 0)
    out[flip] = -out[flip]
    return logodds.to_fixed(out)


def make_case(seed: int, params: mp.MatchParams, laser: bool = False, shift: float = 10.0,
              rot_deg: float = 10.0) -> Case:
    """A seeded misaligned ISM: random place (in free space), heading, shift and rotation."""
    plan = synthetic_floorplan(PLAN, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    lo = params.window_margin(ISM, ISM) + ISM * 0.75
    while True:
        cx, cy = rng.uniform(lo, PLAN - lo, size=2)
        if plan[int(cy), int(cx)] < 0:
            break
    yaw = rng.uniform(-math.pi, math.pi)
    r, a = rng.uniform(0.0, shift), rng.uniform(0.0, 2 * math.pi)
    dyaw = math.radians(rng.uniform(-rot_deg, rot_deg))
    truth = grid_at(cx, cy, yaw)
    claimed = grid_at(cx + r * math.cos(a), cy + r * math.sin(a), yaw + dyaw)
    plan_geom = GridGeometry(RES, PLAN, PLAN)
    ism = resample_logodds(plan, plan_geom, truth, "nearest")
    if laser:
        ism = laser_view(ism, rng)
    window_geom = mt.match_window(claimed, params)
    window = resample_logodds(plan, plan_geom, window_geom, "biodds")
    return Case(ism, truth, claimed, window_geom, window)


def run_cases(params: mp.MatchParams, laser: bool) -> tuple[list[mt.MatchResult],
                                                           list[tuple[float, float]]]:
    """Results and (centre, heading) errors of the corrected geometry (inf when no model)."""
    results, errors = [], []
    for seed in range(N_CASES):
        case = make_case(seed, params, laser)
        res = case.match(params)
        results.append(res)
        if res.matrix is None:
            errors.append((math.inf, math.inf))
        else:
            errors.append(case.errors(mt.corrected_geometry(case.claimed, case.window_geom, res)))
    return results, errors


def recovered(res: mt.MatchResult, err: tuple[float, float]) -> bool:
    return res.accepted and err[0] <= 1.0 and err[1] <= 1.0


# ---------------------------------------------------------------------------------------------
# Recovery


@pytest.mark.parametrize("model", ["partial_affine", "homography"])
def test_cut_isms_are_recovered_within_a_cell_and_a_degree(model: mp.Model) -> None:
    params = mp.MatchParams(model=model)
    results, errors = run_cases(params, laser=False)
    ok = sum(recovered(r, e) for r, e in zip(results, errors, strict=True))
    assert ok >= math.ceil(0.95 * N_CASES), Counter(r.reason for r in results)
    # The claimed poses were wrong by up to 10 cells / 10 degrees: the matcher did the work.
    shifts = [r.correction.translation for r in results if r.correction is not None]
    assert max(shifts) > 5.0


def test_partial_laser_views_are_recovered_or_refused_never_wrong() -> None:
    """A laser sees one room of the plan: fewer features; what is accepted must be right."""
    params = mp.MatchParams()
    results, errors = run_cases(params, laser=True)
    accepted = [(r, e) for r, e in zip(results, errors, strict=True) if r.accepted]
    wrong = [e for r, e in accepted if not recovered(r, e)]
    assert not wrong
    assert len(accepted) >= 0.6 * N_CASES, Counter(r.reason for r in results)


def test_refinement_makes_partial_views_sub_cell() -> None:
    """ECC refinement: without it the ORB-only estimate of a partial view is off by cells."""
    base = mp.MatchParams()
    cases = [make_case(seed, base, laser=True) for seed in range(12)]
    mean_err = {}
    for refine in (False, True):
        params = replace(base, refine=refine)
        errs = []
        for case in cases:
            res = case.match(params)
            if res.matrix is not None and res.inliers >= params.min_inliers:
                geom = mt.corrected_geometry(case.claimed, case.window_geom, res)
                errs.append(case.errors(geom)[0])
        mean_err[refine] = float(np.mean(errs))
    assert mean_err[True] < 0.5 < mean_err[False]


def test_correct_claim_gives_a_near_zero_accepted_correction() -> None:
    params = mp.MatchParams()
    case = make_case(3, params, shift=0.0, rot_deg=0.0)
    res = case.match(params)
    assert res.accepted, res.reason
    assert res.correction is not None
    assert res.correction.translation < 0.5
    assert abs(math.degrees(res.correction.dtheta)) < 0.5
    assert res.score_after >= res.score_before


def test_accepted_correction_improves_agreement_and_reports_fields() -> None:
    params = mp.MatchParams()
    case = make_case(5, params)
    res = case.match(params)
    assert res.accepted and res.reason == "ok"
    assert res.score_after > res.score_before + 0.1
    assert res.inliers >= params.min_inliers and res.n_matches >= res.inliers
    assert res.n_features_ism > 0 and res.n_features_map > 0
    assert res.elapsed_s > 0.0
    assert res.matrix is not None and res.affine is not None and res.affine.shape == (2, 3)
    # The correction maps the claimed placement (prior) onto the found one (matrix).
    c = mt.ism_centre(case.ism.shape)[None]
    moved = mt.apply(res.matrix, c) - mt.apply(res.prior, c)
    assert res.correction is not None
    np.testing.assert_allclose(moved[0], [res.correction.dx, res.correction.dy], atol=1e-9)


def test_matching_is_deterministic() -> None:
    params = mp.MatchParams()
    case = make_case(7, params, laser=True)
    a, b = case.match(params), case.match(params)
    assert a.reason == b.reason and a.inliers == b.inliers
    assert a.matrix is not None and b.matrix is not None
    np.testing.assert_array_equal(a.matrix, b.matrix)


def test_int_fixed_point_and_float_nats_give_the_same_match() -> None:
    params = mp.MatchParams()
    case = make_case(9, params)
    a = case.match(params)
    b = mt.match_ism(logodds.from_fixed(case.ism), logodds.from_fixed(case.window), params,
                     mt.prior_matrix(case.claimed, case.window_geom))
    assert a.matrix is not None and b.matrix is not None
    np.testing.assert_allclose(a.matrix, b.matrix, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Refusals


def test_featureless_isms_are_refused() -> None:
    """Empty floor (or nothing known) has no structure: never 'corrected' at random."""
    params = mp.MatchParams()
    floor = logodds.to_fixed(np.full((ISM, ISM), -2.0))
    nothing = np.zeros((ISM, ISM), np.int16)
    rng = np.random.default_rng(0)
    speckle = logodds.to_fixed(np.where(rng.random((ISM, ISM)) < 0.001, 2.0, -2.0))
    for seed in range(10):
        window = make_case(seed, params).window
        empty_window = logodds.to_fixed(np.full(window.shape, -2.0))
        for ism in (floor, nothing, speckle):
            for win in (window, empty_window):
                res = mt.match_ism(ism, win, params)
                assert not res.accepted, (seed, res.reason, res.correction)


def test_an_ism_from_elsewhere_is_refused() -> None:
    """The window of the claimed pose shows another place: no transform may be accepted."""
    params = mp.MatchParams()
    reasons: Counter[mp.MatchReason] = Counter()
    for seed in range(20):
        plan = synthetic_floorplan(PLAN, seed=seed)
        plan_geom = GridGeometry(RES, PLAN, PLAN)
        here, there = grid_at(140, 140, 0.3 * seed), grid_at(460, 440, 0.3 * seed)
        ism = resample_logodds(plan, plan_geom, here, "nearest")
        if seed % 2:
            ism = laser_view(ism, np.random.default_rng(seed))
        wg = mt.match_window(there, params)
        win = resample_logodds(plan, plan_geom, wg, "biodds")
        res = mt.match_ism(ism, win, params, mt.prior_matrix(there, wg))
        reasons[res.reason] += 1
        assert not res.accepted, (seed, res.correction, res.score_before, res.score_after)
    assert mp.MatchReason.OK not in reasons


def test_acceptance_rules() -> None:
    p = mp.MatchParams(max_translation=5.0, max_rotation=math.radians(3), min_inliers=8)
    ok = mt.Correction(3.0, -3.0, math.radians(2), 1.01)
    assert mt.check_correction(ok, 0.0, 8, p) is None
    assert mt.check_correction(ok, 0.0, 7, p) is mp.MatchReason.TOO_FEW_INLIERS
    far = mt.Correction(4.0, 4.0, 0.0, 1.0)
    assert mt.check_correction(far, 0.0, 8, p) is mp.MatchReason.CORRECTION_TOO_LARGE
    turned = mt.Correction(0.0, 0.0, math.radians(-4), 1.0)
    assert mt.check_correction(turned, 0.0, 8, p) is mp.MatchReason.CORRECTION_TOO_LARGE
    scaled = mt.Correction(0.0, 0.0, 0.0, 1.2)
    assert mt.check_correction(scaled, 0.0, 8, p) is mp.MatchReason.DEGENERATE
    assert mt.check_correction(ok, 5.0, 8, p) is mp.MatchReason.DEGENERATE


def test_a_shift_beyond_the_bounds_is_not_accepted() -> None:
    """Claimed 14 cells off while only 4 are allowed: refused (not found or too large)."""
    params = mp.MatchParams(max_translation=4.0)
    case = make_case(2, params, shift=0.0, rot_deg=0.0)
    off = Pose2D(14 * RES, 0.0, 0.0)
    claimed = GridGeometry(RES, ISM, ISM, off.compose(case.truth.origin))
    wg = mt.match_window(claimed, params)
    plan = synthetic_floorplan(PLAN, seed=2)
    win = resample_logodds(plan, GridGeometry(RES, PLAN, PLAN), wg, "biodds")
    res = mt.match_ism(case.ism, win, params, mt.prior_matrix(claimed, wg))
    assert not res.accepted
    loose = mt.match_ism(case.ism, win, mp.MatchParams(), mt.prior_matrix(claimed, wg))
    assert loose.accepted  # the same pair is matched when 14 cells are allowed


def test_worse_agreement_is_refused() -> None:
    p = mp.MatchParams(min_overlap=10)
    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 50)).astype(np.float32) * 2
    assert mt._verdict(0.8, 0.7, 2500, p) is mp.MatchReason.NO_IMPROVEMENT
    assert mt._verdict(0.5, 0.7, 2500, p) is mp.MatchReason.OK
    assert mt._verdict(0.1, 0.2, 2500, p) is mp.MatchReason.POOR_AGREEMENT
    assert mt._verdict(0.1, 0.9, 5, p) is mp.MatchReason.TOO_LITTLE_OVERLAP
    assert mt._verdict(math.nan, 0.9, 2500, p) is mp.MatchReason.OK
    assert mt._verdict(0.5, math.nan, 2500, p) is mp.MatchReason.POOR_AGREEMENT
    assert mt.agreement(a, a, p)[0] == pytest.approx(1.0)
    assert mt.agreement(a, -a, p)[0] == pytest.approx(-1.0)


# ---------------------------------------------------------------------------------------------
# Pieces


def test_agreement_counts_only_cells_known_in_both() -> None:
    p = mp.MatchParams(min_overlap=4)
    a = np.array([[2.0, -2.0, 0.0, 2.0], [-2.0, 2.0, 0.0, -2.0]], np.float32)
    b = np.array([[2.0, -2.0, 5.0, 0.0], [-2.0, 2.0, -5.0, 0.0]], np.float32)
    score, n = mt.agreement(a, b, p)
    assert n == 4 and score == pytest.approx(1.0)
    const = np.full_like(a, -2.0)
    assert math.isnan(mt.agreement(const, b, p)[0])  # nothing to judge on an empty floor
    assert math.isnan(mt.agreement(a, b, replace(p, min_overlap=5))[0])


def test_render_keeps_free_unknown_occupied_distinct() -> None:
    p = mp.MatchParams(blur_sigma=0.0)
    img = mt.render_u8(np.array([[-3.0, -0.1, 0.0, 0.1, 3.0]], np.float32), p)
    assert img.dtype == np.uint8
    assert list(img[0]) == [p.free_level, p.unknown_level, p.unknown_level, p.unknown_level,
                            p.occupied_level]
    assert len({p.free_level, p.unknown_level, p.occupied_level}) == 3


def test_fit_similarity_recovers_a_known_transform() -> None:
    rng = np.random.default_rng(0)
    src = rng.uniform(-50, 50, size=(20, 2))
    th, s, t = 0.3, 1.1, np.array([4.0, -7.0])
    rot = s * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    m = mt.fit_similarity(src, src @ rot.T + t)
    np.testing.assert_allclose(m[:2, :2], rot, atol=1e-12)
    np.testing.assert_allclose(m[:2, 2], t, atol=1e-9)


def test_corrected_geometry_applies_the_matrix() -> None:
    """Build a result by hand: the corrected geometry must be the truth exactly."""
    params = mp.MatchParams()
    truth = grid_at(300.0, 250.0, 0.4)
    claimed = grid_at(307.0, 244.0, 0.4 + math.radians(6))
    wg = mt.match_window(claimed, params)
    matrix = mt.prior_matrix(truth, wg)  # where the ISM's cells truly are in the window
    res = mt.MatchResult(True, mp.MatchReason.OK, None, matrix, mt.prior_matrix(claimed, wg),
                         0, 0, 0, 0, 0.0, 0.0, 0.0)
    geom = mt.corrected_geometry(claimed, wg, res)
    assert geom.resolution == pytest.approx(RES)
    np.testing.assert_allclose(geom.cell_to_world(), truth.cell_to_world(), atol=1e-9)
    # Identity correction: the claimed geometry comes back.
    same = replace(res, matrix=res.prior)
    np.testing.assert_allclose(mt.corrected_geometry(claimed, wg, same).cell_to_world(),
                               claimed.cell_to_world(), atol=1e-9)
    # A scale is dropped by default (about the centre) and kept on request.
    scaled = np.diag([1.02, 1.02, 1.0]) @ matrix
    res_s = replace(res, matrix=scaled)
    assert mt.corrected_geometry(claimed, wg, res_s).resolution == pytest.approx(RES)
    kept = mt.corrected_geometry(claimed, wg, res_s, keep_scale=True)
    assert kept.resolution == pytest.approx(1.02 * RES)
    with pytest.raises(ValueError, match="no transform"):
        mt.corrected_geometry(claimed, wg, replace(res, matrix=None))


def test_default_prior_is_the_match_window_prior() -> None:
    params = mp.MatchParams()
    claimed = grid_at(300.0, 250.0, 1.0, n=100)
    wg = mt.match_window(claimed, params)
    np.testing.assert_allclose(mt.prior_matrix(claimed, wg),
                               mt.default_prior(claimed.shape, wg.shape), atol=1e-9)


def test_params_are_validated() -> None:
    with pytest.raises(ValueError):
        mp.MatchParams(model="affine")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        mp.MatchParams(min_inliers=2)
    with pytest.raises(ValueError):
        mp.MatchParams(unknown_level=0)
    with pytest.raises(ValueError):
        mp.MatchParams(refine_stages=((0, 4),))
    with pytest.raises(ValueError):
        mt.match_ism(np.zeros(5), np.zeros((5, 5)))


@pytest.mark.parametrize("shape", [(0, 0), (0, 7), (1, 1), (9, 9)])
def test_empty_or_tiny_grids_are_refused_not_raised(shape: tuple[int, int]) -> None:
    tiny = np.zeros(shape, np.int16)
    other = synthetic_floorplan(128, seed=1)
    assert mt.match_ism(tiny, other).reason is mp.MatchReason.TOO_FEW_FEATURES
    assert mt.match_ism(other, tiny).reason is mp.MatchReason.TOO_FEW_FEATURES


def test_ratio_test_option_still_recovers_cut_isms() -> None:
    params = mp.MatchParams(ratio=0.8, cross_check=False)
    for seed in range(6):
        case = make_case(seed, params)
        res = case.match(params)
        assert recovered(res, case.errors(mt.corrected_geometry(case.claimed, case.window_geom,
                                                                 res))), res.reason


def test_floorplan_is_seeded_and_structured() -> None:
    a, b = synthetic_floorplan(256, seed=4), synthetic_floorplan(256, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, synthetic_floorplan(256, seed=5))
    occupied = (a > 0).mean()
    assert 0.02 < occupied < 0.3 and (a < 0).mean() > 0.5 and (a == 0).any()


def test_benchmark_match_returns_timings() -> None:
    out = benchmark_match(size=128, repeats=2, seed=1)
    assert out["accepted"] == 1.0 and out["repeats"] == 2.0
    assert 0.0 < out["min_s"] <= out["mean_s"]


# ---------------------------------------------------------------------------------------------
# The real Intel Research Lab log


INTEL_RES = 0.05
INTEL_RANGE = 8.0  # usable laser range (m): the ISM stays a few hundred cells wide


def _fuse_into(state: npt.NDArray[np.int16], map_geom: GridGeometry, geom: GridGeometry,
               l: npt.NDArray[np.int16]) -> None:
    """Bayes-update only the map block under the ISM (Eq. 1), not the whole map."""
    xmin, ymin, xmax, ymax = geom.bounds()
    (u0, v0), (u1, v1) = map_geom.world_to_index(np.array([[xmin, ymin], [xmax, ymax]]))
    u0, v0 = max(int(u0), 0), max(int(v0), 0)
    u1, v1 = min(int(u1) + 2, map_geom.width), min(int(v1) + 2, map_geom.height)
    block = map_geom.subgrid(u0, v0, u1 - u0, v1 - v0)
    inc = resample_logodds(l, geom, block, "biodds")
    view = state[v0:v1, u0:u1]
    logodds.bayes_update(view, inc, logodds.clamp_limits())


@needs_intel
def test_intel_perturbed_isms_end_closer_to_the_corrected_poses() -> None:
    """Map the log's corrected poses incrementally; every 10th scan (after a warm-up) is first
    sent with a perturbed pose (up to 0.3 m = 6 cells, 5 degrees) and matched against the map
    built so far.  Refused matches keep the perturbed pose (what the server fuses)."""
    scans = list(read_carmen(INTEL_LOG, limit=700))
    xy = np.array([[s.pose.x, s.pose.y] for s in scans])
    lo = np.floor(xy.min(axis=0) - INTEL_RANGE - 2)
    size = np.ceil((xy.max(axis=0) + INTEL_RANGE + 2 - lo) / INTEL_RES).astype(int)
    map_geom = GridGeometry(INTEL_RES, int(size[0]), int(size[1]),
                            Pose2D(float(lo[0]), float(lo[1]), 0.0))
    state = np.zeros(map_geom.shape, np.int16)
    params = mp.MatchParams()
    rng = np.random.default_rng(0)

    def ism(scan: LaserScan, pose: Pose2D) -> tuple[GridGeometry, npt.NDArray[np.int16]]:
        g, p = laser_ism(scan.ranges, scan.angles, pose, INTEL_RES,
                         min(INTEL_RANGE, scan.max_range), device_max_range=scan.max_range)
        return g, logodds.prob_to_fixed(p)

    before, after = [], []
    reasons: Counter[mp.MatchReason] = Counter()
    for i, scan in enumerate(scans):
        if i >= 150 and i % 10 == 0:
            d = rng.uniform(-1.0, 1.0, 3) * np.array([0.3, 0.3, math.radians(5.0)])
            claimed = Pose2D(scan.pose.x + d[0], scan.pose.y + d[1], scan.pose.yaw + d[2])
            g, l = ism(scan, claimed)
            wg = mt.match_window(g, params)
            res = mt.match_ism(l, resample_logodds(state, map_geom, wg, "biodds"), params,
                               mt.prior_matrix(g, wg))
            reasons[res.reason] += 1
            est = claimed
            if res.accepted:
                # The sensor sits at a fixed place in its ISM grid: carry it along.
                to_sensor = g.origin.inverse().compose(claimed)
                est = mt.corrected_geometry(g, wg, res).origin.compose(to_sensor)
            before.append(pose_error(claimed, scan.pose))
            after.append(pose_error(est, scan.pose))
        _fuse_into(state, map_geom, *ism(scan, scan.pose))
    b, a = np.array(before), np.array(after)
    accepted = np.any(a != b, axis=1)
    assert accepted.mean() >= 0.4, reasons
    # Position (m) and heading (deg): the mean error at least a third smaller overall ...
    assert a[:, 0].mean() < 0.67 * b[:, 0].mean()
    assert a[:, 1].mean() < 0.67 * b[:, 1].mean()
    # ... and the accepted corrections land within a cell or two and a degree of the truth.
    assert np.median(a[accepted, 0]) < 2 * INTEL_RES
    assert np.median(a[accepted, 1]) < 1.0


def pose_error(a: Pose2D, b: Pose2D) -> tuple[float, float]:
    """(position error in m, heading error in degrees)."""
    return math.hypot(a.x - b.x, a.y - b.y), abs(math.degrees(math.remainder(a.yaw - b.yaw,
                                                                             2 * math.pi)))


def test_a_map_aligned_window_also_works() -> None:
    """The window need not be in the ISM's frame: any window with its prior matrix will do."""
    params = mp.MatchParams()
    plan = synthetic_floorplan(PLAN, seed=11)
    plan_geom = GridGeometry(RES, PLAN, PLAN)
    ok = 0
    for k in range(8):
        truth = grid_at(320 + 5 * k, 300 - 4 * k, 0.6 + 0.4 * k)
        claimed = grid_at(326 + 5 * k, 296 - 4 * k, 0.6 + 0.4 * k + math.radians(6))
        m = params.window_margin(ISM, ISM) + ISM
        wg = plan_geom.subgrid(320 - m, 300 - m, 2 * m, 2 * m)  # map axes, not the ISM's
        win = resample_logodds(plan, plan_geom, wg, "biodds")
        ism = resample_logodds(plan, plan_geom, truth, "nearest")
        res = mt.match_ism(ism, win, params, mt.prior_matrix(claimed, wg))
        if res.accepted:
            err = centre_error(mt.corrected_geometry(claimed, wg, res), truth)
            ok += err <= 1.0
    assert ok >= 7


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-50, 50), y=st.floats(-50, 50), yaw=st.floats(-math.pi, math.pi),
       dx=st.floats(-1, 1), dy=st.floats(-1, 1), dyaw=st.floats(-0.3, 0.3),
       w=st.integers(3, 300), h=st.integers(3, 300))
def test_corrected_geometry_recovers_any_true_geometry(x: float, y: float, yaw: float,
                                                      dx: float, dy: float, dyaw: float,
                                                      w: int, h: int) -> None:
    """For any claimed/true pair, a match that found the true placement yields the truth."""
    truth = GridGeometry(0.1, w, h, Pose2D(x, y, yaw))
    claimed = GridGeometry(0.1, w, h, Pose2D(x + dx, y + dy, yaw + dyaw))
    wg = mt.match_window(claimed, mp.MatchParams())
    res = mt.MatchResult(True, mp.MatchReason.OK, None, mt.prior_matrix(truth, wg),
                         mt.prior_matrix(claimed, wg), 0, 0, 0, 0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(mt.corrected_geometry(claimed, wg, res).cell_to_world(),
                               truth.cell_to_world(), atol=1e-7)
    corr, distortion = mt.correction_of(mt.prior_matrix(truth, wg), res.prior, (h, w))
    assert distortion < 1e-6 and corr.scale == pytest.approx(1.0)
    # The correction turns the claimed heading back onto the true one.
    assert math.remainder(corr.dtheta + dyaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    # The shift is the claimed -> true displacement of the ISM's centre, in cells.
    assert corr.translation * 0.1 == pytest.approx(
        float(np.hypot(*(centre(truth) - centre(claimed)))), abs=1e-7)


def test_summary_is_json_ready() -> None:
    params = mp.MatchParams()
    good = make_case(5, params).match(params)
    assert good.correction is not None and good.matrix is not None
    out = json.loads(json.dumps(good.summary(), allow_nan=False))
    assert out["accepted"] is True and out["reason"] == "ok"
    assert out["correction"]["dx"] == pytest.approx(good.correction.dx)
    assert np.allclose(out["matrix"], good.matrix)
    bad = mt.match_ism(np.zeros((ISM, ISM), np.int16), make_case(5, params).window, params)
    out = json.loads(json.dumps(bad.summary(), allow_nan=False))
    assert out["accepted"] is False and out["reason"] == "too_few_features"
    assert out["correction"] is None and out["score_after"] is None
