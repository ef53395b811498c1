"""Resampling (resample.py): biodds against a literal Eq. 5, its eps0 limits, and geometry.

The Eq. 5 reference below is slow and explicit on purpose: scalar ``math`` calls, the four
sample points ``P00, P01, P10, P11`` and the three nested applications of ``f`` exactly as the
paper prints them, with ``f(x) = 0.5 tanh((x - 0.5) a) + 0.5`` (Eq. 4) and
``a = 2 atanh(1 - 2 eps0)``, which makes ``f`` map the normalised evidence ``x in [0, 1]`` onto
the bounds ``[eps0, 1 - eps0]`` of Eq. 3.  Cell values are therefore first limited to those
bounds (outside them ``f^-1`` leaves ``[0, 1]``).

Positions follow geometry.py: cell centres on integers, ``P_xy`` with ``x`` the column and ``y``
the row, ``P00`` the lower-left neighbour of the sample point.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sogm_service.core import logodds
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.resample import (
    INTERPOLATIONS,
    dst_to_src,
    resample_logodds,
    resample_stack,
    warp,
)
from tests.oracles import resample_prob, sample_bilinear

# -- the paper's Eq. 3-5, literally --------------------------------------------------------


def eq5_reference(grid: np.ndarray, x: float, y: float, eps0: float) -> float:
    """Biodds interpolation of ``grid`` (probabilities, ``[row, col]``) at cell coords (x, y)."""
    a = 2.0 * math.atanh(1.0 - 2.0 * eps0)

    def f(t: float) -> float:  # Eq. 4
        return 0.5 * math.tanh((t - 0.5) * a) + 0.5

    def f_inv(m: float) -> float:
        return 0.5 + math.atanh(2.0 * m - 1.0) / a

    def m_at(col: int, row: int) -> float:  # a grid value, limited to the bounds of Eq. 3
        return min(max(float(grid[row, col]), eps0), 1.0 - eps0)

    # the cell square holding P; on the last row/column, the square that ends there
    x0 = min(math.floor(x), grid.shape[1] - 2)
    y0 = min(math.floor(y), grid.shape[0] - 2)
    x1, y1 = x0 + 1, y0 + 1
    p00, p10 = m_at(x0, y0), m_at(x1, y0)
    p01, p11 = m_at(x0, y1), m_at(x1, y1)
    m1 = f((x - x0) / (x1 - x0) * f_inv(p11) + (x1 - x) / (x1 - x0) * f_inv(p01))
    m0 = f((x - x0) / (x1 - x0) * f_inv(p10) + (x1 - x) / (x1 - x0) * f_inv(p00))
    return f((y - y0) / (y1 - y0) * f_inv(m1) + (y1 - y) / (y1 - y0) * f_inv(m0))


def exact_biodds(grid: np.ndarray, u: np.ndarray, v: np.ndarray, eps0: float) -> np.ndarray:
    """The fast formula in float64: sigmoid(bilinear(logit(clip(p))))."""
    l = logodds.logit(np.clip(grid, eps0, 1 - eps0))
    return logodds.sigmoid(sample_bilinear(l, u, v, 0.0))


def plain_bilinear(grid: np.ndarray, x: float, y: float) -> float:
    x0 = min(math.floor(x), grid.shape[1] - 2)
    y0 = min(math.floor(y), grid.shape[0] - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * grid[y0, x0] + fx * (1 - fy) * grid[y0, x0 + 1]
            + (1 - fx) * fy * grid[y0 + 1, x0] + fx * fy * grid[y0 + 1, x0 + 1])


def inner_points(rng: np.random.Generator, shape: tuple[int, int], n: int) -> tuple:
    """Random sample positions whose four neighbours all lie inside the grid."""
    return (rng.uniform(0, shape[1] - 1, n), rng.uniform(0, shape[0] - 1, n))


# -- the fast paths against Eq. 5 ----------------------------------------------------------


@pytest.mark.parametrize("eps0", [1e-6, 0.001, 0.05, 0.3, 0.45])
def test_eq5_reference_equals_exact_fast_formula(eps0: float) -> None:
    rng = np.random.default_rng(5)
    grid = rng.uniform(0, 1, (7, 9))
    grid[0, :3] = [0.0, 1.0, 0.5]  # certain cells are limited to the bounds first
    u, v = inner_points(rng, grid.shape, 300)
    u[:4], v[:4] = [0, 8, 3, 2.5], [0, 6, 2, 0.5]  # on cell centres and on a cell edge
    ref = np.array([eq5_reference(grid, x, y, eps0) for x, y in zip(u, v, strict=True)])
    np.testing.assert_allclose(exact_biodds(grid, u, v, eps0), ref, rtol=0, atol=1e-12)


def _aligned_target(src: GridGeometry, du: float, dv: float, scale: float) -> GridGeometry:
    """A target grid whose cell centres sit on source cell coords ``du + k * scale``."""
    res = src.resolution * scale
    # target centre k -> source coord du + k*scale  <=>  corner at source coord du - scale/2
    corner = ((du - 0.5 * scale + 0.5) * src.resolution,
              (dv - 0.5 * scale + 0.5) * src.resolution)
    w = int((src.width - 1 - du) / scale) + 1
    h = int((src.height - 1 - dv) / scale) + 1
    return GridGeometry(res, w, h, Pose2D(src.origin.x + corner[0], src.origin.y + corner[1]))


@pytest.mark.parametrize("eps0", [1e-4, 0.001, 0.1])
def test_opencv_biodds_equals_eq5_on_exactly_representable_positions(eps0: float) -> None:
    # Offsets and steps that are multiples of 1/32 cell are not quantised by OpenCV, so the
    # warp must agree with Eq. 5 up to float32 arithmetic.
    rng = np.random.default_rng(32)
    grid = rng.uniform(0, 1, (12, 14))
    src = GridGeometry(0.1, 14, 12, Pose2D(2.0, -1.0, 0.0))
    for du, dv, scale in [(0.5, 0.5, 1.0), (0.25, 0.75, 0.5), (0.5, 0.0, 1.5), (3 / 32, 0, 1)]:
        dst = _aligned_target(src, du, dv, scale)
        got = resample_prob(grid, src, dst, "biodds", eps0)
        uu, vv = np.meshgrid(du + scale * np.arange(dst.width), dv + scale * np.arange(dst.height))
        ref = np.array([eq5_reference(grid, x, y, eps0)
                        for x, y in zip(uu.ravel(), vv.ravel(), strict=True)]).reshape(uu.shape)
        # float32 logit/warp/sigmoid: dp = p(1-p) dl with dl ~ 1e-6 * |l|
        np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6)


def test_opencv_biodds_equals_eq5_within_quantisation_on_any_geometry() -> None:
    rng = np.random.default_rng(33)
    eps0 = 0.01
    grid = rng.uniform(0, 1, (20, 20))
    src = GridGeometry(0.1, 20, 20, Pose2D(0.3, 0.7, 0.2))
    dst = GridGeometry(0.073, 17, 15, Pose2D(0.6, 0.9, 0.9))
    got = resample_prob(grid, src, dst, "biodds", eps0)
    m = dst_to_src(src, dst)
    l = logodds.logit(np.clip(grid, eps0, 1 - eps0))
    checked = 0
    for r in range(dst.height):
        for c in range(dst.width):
            x, y, _ = m @ np.array([c, r, 1.0])
            if not (0 <= x < src.width - 1 and 0 <= y < src.height - 1):
                continue
            ref = eq5_reference(grid, x, y, eps0)
            x0, y0 = math.floor(x), math.floor(y)
            spread = np.ptp(l[y0:y0 + 2, x0:x0 + 2])
            # OpenCV rounds the position to 1/32 cell per axis: the log-odds move by at most
            # spread/32 per axis, the probability by at most a quarter of that.
            tol = 0.25 * spread * 2 / 32 + 2e-6
            assert abs(got[r, c] - ref) <= tol, (r, c)
            checked += 1
    assert checked > 100


def test_fixed_point_biodds_equals_eq5_in_logodds() -> None:
    rng = np.random.default_rng(34)
    eps0 = 0.001
    grid = rng.uniform(0, 1, (10, 10))
    src = GridGeometry(0.2, 10, 10)
    dst = _aligned_target(src, 0.5, 0.25, 0.5)
    stored = logodds.prob_to_fixed(grid, eps0)  # what the map holds
    got = resample_logodds(stored, src, dst, "biodds")
    for r in range(dst.height):
        for c in range(dst.width):
            ref = eq5_reference(grid, 0.5 + 0.5 * c, 0.25 + 0.5 * r, eps0)
            ref_l = math.log(ref / (1 - ref)) * logodds.SCALE
            # half a unit from storing the cells, half from rounding the result, + OpenCV's
            # 15-bit fixed-point weights on int16
            assert abs(got[r, c] - ref_l) <= 1.5, (r, c)


def test_warp_matches_sample_bilinear_including_borders() -> None:
    rng = np.random.default_rng(35)
    grid = rng.uniform(-3, 3, (9, 11)).astype(np.float32)
    src = GridGeometry(0.5, 11, 9, Pose2D(1.0, 2.0, -0.4))
    dst = GridGeometry(0.31, 24, 22, Pose2D(-0.5, 0.5, 0.3))  # reaches beyond src
    got = warp(grid, src, dst, "linear", 0.0)
    m = dst_to_src(src, dst)
    uu, vv = np.meshgrid(np.arange(dst.width), np.arange(dst.height))
    su = m[0, 0] * uu + m[0, 1] * vv + m[0, 2]
    sv = m[1, 0] * uu + m[1, 1] * vv + m[1, 2]
    ref = sample_bilinear(grid, su, sv, 0.0)
    # 1/32-cell quantisation per axis, a neighbour difference of at most 6 (+ the border 0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=6 * 2 / 32 + 1e-5)
    outside = (su < -1) | (sv < -1) | (su > src.width) | (sv > src.height)
    assert outside.sum() > 20 and (got[outside] == 0).all()


# -- the limits of eps0 (paper Fig. 3) -----------------------------------------------------
#
# What is provable from Eq. 5 = sigmoid(bilinear(logit(clip(p, eps0, 1 - eps0)))):
#
# * eps0 -> 0.5: with d = 0.5 - eps0, cells limited/rescaled into the bounds
#   q = eps0 + (1 - 2 eps0) p give (biodds(q) - eps0) / (1 - 2 eps0) = bilinear(p) + O(d^2)
#   (logit and sigmoid are linear up to cubic terms around 0.5; the constant is below 2).
#   For cells of opposite certainty (p in {0, 1}) the clamp *is* that rescaling.
# * eps0 -> 0, cells of opposite certainty: the log-odds are +-L with L = logit(1 - eps0),
#   so biodds = sigmoid(L (2 w - 1)) with w = bilinear(p): a step at w = 1/2 approached
#   as |biodds - step| <= (eps0 / (1 - eps0))^|2w - 1|.  Between two cells (or across an edge
#   that is constant along one axis) w = 1/2 is the midpoint, so the step *is* nearest
#   neighbour.  At a corner of a single certain cell it is not (tested below, honestly).
# * eps0 -> 0 does nothing to uncertain cells: once eps0 < min(p, 1 - p) it only clamps.


@pytest.mark.parametrize("d", [0.1, 0.03, 0.01, 0.003])
def test_eps0_to_half_is_bilinear_after_rescaling(d: float) -> None:
    rng = np.random.default_rng(50)
    eps0 = 0.5 - d
    p = rng.uniform(0, 1, (6, 6))
    q = eps0 + (1 - 2 * eps0) * p  # the grid rescaled into the bounds of Eq. 3
    u, v = inner_points(rng, p.shape, 200)
    for x, y in zip(u, v, strict=True):
        rescaled = (eq5_reference(q, x, y, eps0) - eps0) / (1 - 2 * eps0)
        assert abs(rescaled - plain_bilinear(p, x, y)) <= 2 * d * d


def test_eps0_to_half_on_certain_cells_through_opencv() -> None:
    rng = np.random.default_rng(51)
    grid = (rng.random((10, 10)) < 0.5).astype(np.float64)  # opposite certainties only
    src = GridGeometry(1.0, 10, 10)
    dst = _aligned_target(src, 0.25, 0.5, 0.75)
    bil = resample_prob(grid, src, dst, "bilinear")
    errors = []
    for d in (0.1, 0.05, 0.02):
        eps0 = 0.5 - d
        bio = resample_prob(grid, src, dst, "biodds", eps0).astype(np.float64)
        err = np.abs((bio - eps0) / (1 - 2 * eps0) - bil).max()
        # float32 logit/sigmoid noise is amplified by 1 / (1 - 2 eps0)
        assert err <= 2 * d * d + 1e-6 / d
        errors.append(err)
    assert errors[0] > errors[1] > errors[2]
    # and far from the limit it is clearly not bilinear: the limit is a real limit
    bio = resample_prob(grid, src, dst, "biodds", 0.001)
    assert np.abs(bio - bil).max() > 0.2


def test_eps0_to_zero_is_nearest_between_two_cells_of_opposite_certainty() -> None:
    # Columns alternate free/occupied: every 2x2 neighbourhood is constant along y, the 1-D
    # situation of Fig. 3 (two cells of opposite certainty).
    grid = np.tile(np.array([0.0, 1.0, 1.0, 0.0, 1.0, 0.0]), (5, 1))
    src = GridGeometry(1.0, 6, 5)
    dst = _aligned_target(src, 1 / 32, 0.0, 3 / 32)  # sub-cell steps of 3/32, all exact
    near = resample_prob(grid, src, dst, "nearest")
    uu = 1 / 32 + 3 / 32 * np.arange(dst.width)
    frac = np.abs(uu - np.floor(uu) - 0.5)  # distance of the sample from the midpoint
    frac = np.broadcast_to(frac, dst.shape)
    previous = None
    for eps0 in (1e-2, 1e-4, 1e-6, logodds.MIN_EPS0):
        bio = resample_prob(grid, src, dst, "biodds", eps0).astype(np.float64)
        # sigmoid(-L x) = r^x / (1 + r^x) <= r^x, r = eps0 / (1 - eps0); + float32 noise
        bound = (eps0 / (1 - eps0)) ** (2 * frac) + 1e-6
        assert (np.abs(bio - near) <= bound).all(), eps0
        err = np.abs(bio - near)[frac >= 0.1].max()
        if previous is not None:
            assert err < previous
        previous = err
    assert previous is not None and previous < 0.05  # r^0.2 at the smallest eps0


def test_eps0_to_zero_at_a_corner_is_a_bilinear_threshold_not_nearest() -> None:
    # A single occupied cell among free ones: at (0.4, 0.4) from it the nearest cell is the
    # occupied one, but the bilinear weight is 0.36 < 1/2, so biodds tends to *free*.
    grid = np.zeros((2, 2))
    grid[0, 0] = 1.0
    for eps0 in (1e-3, 1e-6, 1e-9):
        assert eq5_reference(grid, 0.4, 0.4, eps0) < (eps0 / (1 - eps0)) ** 0.28 + 1e-12
    # on the bilinear weight's far side of 1/2 it tends to occupied: (0.2, 0.2) -> w = 0.64
    assert eq5_reference(grid, 0.2, 0.2, 1e-9) > 1 - (1e-9) ** 0.28


def test_eps0_does_not_change_uncertain_cells() -> None:
    rng = np.random.default_rng(52)
    grid = rng.uniform(0.2, 0.8, (8, 8))
    u, v = inner_points(rng, grid.shape, 100)
    a = exact_biodds(grid, u, v, 1e-3)
    b = exact_biodds(grid, u, v, 1e-9)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)


# -- geometry ------------------------------------------------------------------------------


def world_of_cell(origin: Pose2D, res: float, col: float, row: float) -> np.ndarray:
    """Cell centre in the parent frame, by hand: origin + R(yaw) ((col + .5) r, (row + .5) r)."""
    lx, ly = (col + 0.5) * res, (row + 0.5) * res
    c, s = math.cos(origin.yaw), math.sin(origin.yaw)
    return np.array([origin.x + c * lx - s * ly, origin.y + s * lx + c * ly])


def cell_of_world(origin: Pose2D, res: float, xy: np.ndarray) -> tuple[int, int]:
    dx, dy = xy[0] - origin.x, xy[1] - origin.y
    c, s = math.cos(origin.yaw), math.sin(origin.yaw)
    return math.floor((c * dx + s * dy) / res), math.floor((-s * dx + c * dy) / res)


def test_cell_to_world_agrees_with_hand_computation() -> None:
    g = GridGeometry(0.25, 7, 5, Pose2D(1.5, -2.0, 0.7))
    for col, row in [(0, 0), (6, 4), (3, 1)]:
        got = (g.cell_to_world() @ np.array([col, row, 1.0]))[:2]
        np.testing.assert_allclose(got, world_of_cell(g.origin, 0.25, col, row), atol=1e-12)
        assert tuple(g.world_to_index(got)) == (col, row)


@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_identity_returns_input_exactly(interp: str) -> None:
    rng = np.random.default_rng(60)
    g = GridGeometry(0.05, 13, 11, Pose2D(3.0, -4.0, 1.1))
    lo, hi = logodds.clamp_limits(logodds.MIN_EPS0)  # the widest clamp a map can have
    l = rng.integers(lo, hi + 1, (11, 13)).astype(np.int16)
    l[0, :3] = [lo, hi, 0]
    np.testing.assert_array_equal(resample_logodds(l, g, g, interp), l)
    p = rng.uniform(0, 1, (11, 13)).astype(np.float32)
    got = resample_prob(p, g, g, interp, 0.001)
    if interp == "biodds":  # the bounds of Eq. 3 apply, then float32 logit/sigmoid
        np.testing.assert_allclose(got, np.clip(p, 0.001, 0.999), rtol=0, atol=1e-6)
    elif interp == "nearest":
        np.testing.assert_array_equal(got, p)
    else:  # OpenCV sums border cells with a zero weight on 0.5: a float32 ulp may move
        np.testing.assert_allclose(got, p, rtol=1e-6, atol=0)


def _single_cell(shape: tuple[int, int], col: int, row: int, value: float) -> np.ndarray:
    g = np.full(shape, 0.2)
    g[row, col] = value
    return g


def _landing(out: np.ndarray, value: float) -> list[tuple[int, int]]:
    rows, cols = np.nonzero(np.abs(out - value) < 1e-4)
    return [(int(c), int(r)) for r, c in zip(rows, cols, strict=True)]


@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_rotation_by_90_degrees_lands_where_geometry_says(interp: str) -> None:
    res = 0.5
    src = GridGeometry(res, 6, 4, Pose2D(1.0, -2.0, 0.3))
    grid = _single_cell(src.shape, 4, 1, 0.9)
    # A target rotated by +90 deg about the source's corner (W r, 0): its cell centres
    # coincide with source cell centres, so every interpolation must reproduce values.
    corner = world_of_cell(src.origin, res, 6 - 0.5, -0.5)
    dst = GridGeometry(res, 4, 6, Pose2D(corner[0], corner[1], 0.3 + math.pi / 2))
    out = resample_prob(grid, src, dst, interp, 0.001)
    hits = _landing(out, 0.9)
    assert len(hits) == 1
    np.testing.assert_allclose(world_of_cell(dst.origin, res, *hits[0]),
                               world_of_cell(src.origin, res, 4, 1), atol=1e-9)
    assert np.allclose(np.delete(out.ravel(), hits[0][1] * 4 + hits[0][0]), 0.2, atol=1e-4)
    # the fixed-point path agrees
    l = logodds.prob_to_fixed(grid)
    np.testing.assert_array_equal(resample_logodds(l, src, dst, "nearest"),
                                  logodds.prob_to_fixed(out if interp == "nearest" else
                                                        resample_prob(grid, src, dst,
                                                                      "nearest")))


def test_upscale_by_two_covers_the_cell_with_four() -> None:
    res = 0.4
    src = GridGeometry(res, 5, 4, Pose2D(-1.0, 0.5, -0.6))
    grid = _single_cell(src.shape, 3, 2, 0.9)
    dst = GridGeometry(res / 2, 10, 8, src.origin)
    out = resample_prob(grid, src, dst, "nearest")
    hits = sorted(_landing(out, 0.9))
    assert len(hits) == 4
    for col, row in hits:  # every marked target centre lies inside the marked source cell
        xy = world_of_cell(dst.origin, res / 2, col, row)
        assert cell_of_world(src.origin, res, xy) == (3, 2)
    # and every target cell whose centre is inside it is marked
    for row in range(8):
        for col in range(10):
            xy = world_of_cell(dst.origin, res / 2, col, row)
            assert (cell_of_world(src.origin, res, xy) == (3, 2)) == ((col, row) in hits)


@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_downscale_by_two_lands_where_geometry_says(interp: str) -> None:
    res = 0.1
    src = GridGeometry(res, 8, 6, Pose2D(2.0, 1.0, 0.25))
    grid = _single_cell(src.shape, 4, 2, 0.9)
    # coarse cells of 2r whose centres sit on the centres of the even source cells
    corner = world_of_cell(src.origin, res, -1, -1)  # the centre of cell (-1, -1)
    dst = GridGeometry(2 * res, 4, 3, Pose2D(corner[0], corner[1], 0.25))
    out = resample_prob(grid, src, dst, interp, 0.001)
    hits = _landing(out, 0.9)
    assert len(hits) == 1
    np.testing.assert_allclose(world_of_cell(dst.origin, 2 * res, *hits[0]),
                               world_of_cell(src.origin, res, 4, 2), atol=1e-9)


@pytest.mark.parametrize("interp", INTERPOLATIONS)
def test_outside_the_source_is_unknown_not_zero(interp: str) -> None:
    src = GridGeometry(0.1, 10, 10, Pose2D(0.0, 0.0, 0.0))
    p = np.full((10, 10), 0.9)
    l = logodds.prob_to_fixed(p)
    # a target twice as wide, shifted half out of the source to the right, slightly rotated
    dst = GridGeometry(0.1, 20, 10, Pose2D(0.5, 0.0, 0.02))
    m = dst_to_src(src, dst)
    uu, vv = np.meshgrid(np.arange(20), np.arange(10))
    su = m[0, 0] * uu + m[0, 1] * vv + m[0, 2]
    sv = m[1, 0] * uu + m[1, 1] * vv + m[1, 2]
    outside = (su > 10.1) | (sv > 10.1) | (su < -1.1) | (sv < -1.1)
    inside = (su >= 0.1) & (su <= 8.9) & (sv >= 0.1) & (sv <= 8.9)
    assert outside.sum() > 50 and inside.sum() > 30
    pr = resample_prob(p, src, dst, interp, 0.001)
    lr = resample_logodds(l, src, dst, interp)
    assert (pr[outside] == 0.5).all()
    assert (lr[outside] == 0).all()
    np.testing.assert_allclose(pr[inside], 0.9, atol=1e-4)
    assert (np.abs(lr[inside] - l[0, 0]) <= 1).all()
    # at the edge values blend toward unknown, never toward 0
    assert (pr >= 0.5 - 1e-6).all() and (lr >= 0).all()
    # a target entirely elsewhere is entirely unknown
    far = GridGeometry(0.1, 5, 5, Pose2D(50.0, 50.0, 1.0))
    assert (resample_prob(p, src, far, interp) == 0.5).all()
    assert (resample_logodds(l, src, far, interp) == 0).all()


@pytest.mark.parametrize("layers", [1, 2, 3, 4, 5, 6, 9])
def test_resample_stack_is_per_layer(layers: int) -> None:
    # The stack path shares the transform, the float conversion and the rounding between
    # layers: each layer must still come out exactly as resampled on its own.
    rng = np.random.default_rng(70 + layers)
    src = GridGeometry(0.1, 29, 17, Pose2D(0.1, 0.2, 0.3))
    dst = GridGeometry(0.15, 16, 13, Pose2D(0.0, 0.0, -0.2))
    stack = rng.integers(-6900, 6900, (layers, 17, 29)).astype(np.int16)
    for interp in INTERPOLATIONS:
        out = resample_stack(stack, src, dst, interp)
        assert out.shape == (layers, 13, 16) and out.dtype == np.int16
        assert out.any()
        for n in range(layers):
            np.testing.assert_array_equal(out[n], resample_logodds(stack[n], src, dst, interp))


def test_bilinear_logodds_interpolates_probabilities() -> None:
    # "bilinear" blends probabilities, unlike biodds: halfway between P=0.1 and P=0.9 it is 0.5
    src = GridGeometry(1.0, 2, 1)
    l = logodds.prob_to_fixed(np.array([[0.99, 0.5]]))
    dst = GridGeometry(1.0, 1, 1, Pose2D(0.5, 0.0, 0.0))  # centre halfway between the two
    got = logodds.fixed_to_prob(resample_logodds(l, src, dst, "bilinear"))[0, 0]
    assert abs(got - 0.745) < 1e-3
    bio = logodds.fixed_to_prob(resample_logodds(l, src, dst, "biodds"))[0, 0]
    assert abs(bio - 1 / (1 + math.sqrt(1 / 99))) < 1e-3  # half the evidence of 0.99


def test_shape_mismatch_and_unknown_interp_are_refused() -> None:
    g = GridGeometry(0.1, 4, 3)
    with pytest.raises(ValueError):
        resample_prob(np.zeros((4, 3)), g, g, "nearest")
    with pytest.raises(ValueError):
        resample_logodds(np.zeros((3, 4), np.int16), g, g, "cubic")  # type: ignore[arg-type]


@pytest.mark.parametrize("eps0", [0.0, -0.1, 0.5, 0.7, math.nan])
def test_biodds_refuses_an_unusable_eps0(eps0: float) -> None:
    # eps0 = 0 would make certain cells +-inf log-odds and their neighbours NaN
    g = GridGeometry(1.0, 2, 1)
    with pytest.raises(ValueError):
        resample_prob(np.array([[1.0, 0.0]]), g, g, "biodds", eps0)


@pytest.mark.parametrize("interp", ["biodds", "nearest"])
def test_tile_patches_are_their_blocks_and_do_not_depend_on_who_fuses(interp: str) -> None:
    """Warped ISMs are warped a band of tiles at a time (one OpenCV call a tile row); every
    patch has its block's shape, and a share of the tiles (a fuse worker's, a cluster
    member's) gets the very bits the whole gets: bands span the footprint whatever is owned."""
    from sogm_service.core.geometry import TileLattice
    from sogm_service.core.resample import tile_patches

    rng = np.random.default_rng(5)
    inc = rng.integers(-3000, 3001, (70, 90)).astype(np.int16)
    ism = GridGeometry(0.07, 90, 70, Pose2D(-1.31, -0.77, 0.6))
    lattice = TileLattice(0.05, 32)
    whole = {p.index: (p.block, p.patch.copy())
             for p in tile_patches(inc, ism, lattice, interp)}  # type: ignore[arg-type]
    assert len({index[1] for index in whole}) >= 3 and len(whole) >= 12
    for block, patch in whole.values():
        assert patch.shape == (block[3], block[2]) and patch.dtype == np.int16
    assert sum(int(np.abs(p).sum()) > 0 for _, p in whole.values()) >= 8
    for k in range(3):  # three workers' shares, as FuseWorkers splits tiles
        share = {p.index: p.patch.copy() for p in tile_patches(
            inc, ism, lattice, interp, owned=lambda i, k=k: (i[0] + i[1]) % 3 == k,  # type: ignore[misc,arg-type]
            buffers=lambda h, w, d: np.empty((h, w), d))}
        assert share and all((i[0] + i[1]) % 3 == k for i in share)
        for index, patch in share.items():
            assert np.array_equal(patch, whole[index][1]), index
