"""Fixed-point log-odds core (logodds.py) against the paper's equations in probability space.

Every reference here is computed independently in float64 probability space (odds products,
maxima), never from the module's own output.  Tolerances are derived from the fixed point:
one unit is ``1 / SCALE`` nat, so a value rounded to the nearest unit is off by at most half a
unit in log-odds, i.e. by at most ``p (1 - p) * 0.5 / SCALE`` in probability.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sogm_service.core import logodds
from sogm_service.core.logodds import MAX_STATE, MIN_EPS0, SCALE, Encoding

HALF_UNIT = 0.5 / SCALE  # nats: the rounding error of one fixed-point conversion
F32 = 2.0**-24  # relative precision of float32 (fixed_to_prob returns float32)

eps0s = st.floats(min_value=MIN_EPS0, max_value=0.5, exclude_max=True, allow_nan=False)


def odds(p: np.ndarray) -> np.ndarray:
    return p / (1.0 - p)


def prob_of_odds(o: np.ndarray) -> np.ndarray:
    return o / (1.0 + o)


def dp_tol(p: np.ndarray, nats: float) -> np.ndarray:
    """Probability error caused by ``nats`` of log-odds error (dp/dl = p (1 - p)), + float32."""
    p = np.asarray(p, dtype=np.float64)
    return p * (1.0 - p) * nats * 1.01 + 2 * F32


# -- Eq. 6 ---------------------------------------------------------------------------------


@pytest.mark.parametrize("n_layers", [1, 2, 3, 5])
def test_eq6_bayes_pool_matches_probability_formula(n_layers: int) -> None:
    rng = np.random.default_rng(6 + n_layers)
    eps0 = 0.001
    p = rng.uniform(eps0, 1 - eps0, size=(n_layers, 40, 30))
    # P_B = 1 / (1 + prod_n (1 - P_n) / P_n), literally as printed in Eq. 6
    expected = 1.0 / (1.0 + np.prod((1.0 - p) / p, axis=0))
    stack = logodds.prob_to_fixed(p, eps0)
    got = logodds.fixed_to_prob(logodds.fuse_bayes(stack)).astype(np.float64)
    np.testing.assert_array_less(np.abs(got - expected), dp_tol(expected, n_layers * HALF_UNIT))


def test_eq6_bayes_pool_of_saturated_layers_does_not_overflow() -> None:
    # 5 layers at the widest clamp sum to ~80 nats: beyond int16, fine in the int32 result.
    lo, hi = logodds.clamp_limits(MIN_EPS0)
    stack = np.full((5, 2, 2), hi, dtype=np.int16)
    stack[:, 1] = lo
    fused = logodds.fuse_bayes(stack)
    assert fused.dtype == np.int32
    assert (fused[0] == 5 * hi).all() and (fused[1] == 5 * lo).all()
    p = logodds.fixed_to_prob(fused)
    assert (p[0] > 0.999999).all() and (p[1] < 1e-6).all()


@pytest.mark.parametrize("n_layers", [1, 2, 4])
def test_eq6_max_pool_matches_probability_max(n_layers: int) -> None:
    rng = np.random.default_rng(60 + n_layers)
    eps0 = 0.001
    p = rng.uniform(eps0, 1 - eps0, size=(n_layers, 30, 20))
    expected = p.max(axis=0)
    got = logodds.fixed_to_prob(logodds.fuse_max(logodds.prob_to_fixed(p, eps0)))
    np.testing.assert_array_less(np.abs(got - expected), dp_tol(expected, HALF_UNIT))
    # and it picks a layer's own value, not a blend
    stack = logodds.prob_to_fixed(p, eps0)
    assert (logodds.fuse_max(stack)[None] == stack).any(axis=0).all()


def test_eq6_pools_with_unknown_layers() -> None:
    # An unknown layer (log-odds exactly 0) has no opinion: neutral in P_B, and in P_M the
    # max is over the layers that observed the cell (a free cell stays free).
    stack = logodds.prob_to_fixed(np.array([[0.2, 0.9], [0.5, 0.5]]))
    assert (stack[1] == 0).all()
    pb = logodds.fixed_to_prob(logodds.fuse_bayes(stack[:, :, None]))[:, 0]
    pm = logodds.fixed_to_prob(logodds.fuse_max(stack[:, :, None]))[:, 0]
    np.testing.assert_allclose(pb, [0.2, 0.9], atol=1e-4)
    np.testing.assert_allclose(pm, [0.2, 0.9], atol=1e-4)


def _max_over_observed(stack: np.ndarray) -> np.ndarray:
    """The reference: per cell, max over the layers whose value is not 0; 0 if there are none."""
    out = np.zeros(stack.shape[1:], dtype=np.int16)
    for idx in np.ndindex(*stack.shape[1:]):
        seen = [int(v) for v in stack[(slice(None), *idx)] if v != 0]
        out[idx] = max(seen) if seen else 0
    return out


def test_eq6_max_pool_ignores_layers_without_evidence_exhaustively() -> None:
    # Every combination of three layers over values of both signs, small and extreme, and 0.
    values = [-MAX_STATE, -6907, -5, -1, 0, 1, 7, 6907, MAX_STATE]
    combos = np.array(np.meshgrid(values, values, values, indexing="ij"), dtype=np.int16)
    stack = combos.reshape(3, -1)
    got = logodds.fuse_max(stack)
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, _max_over_observed(stack))
    # the cells no layer observed, and only those, stay unknown
    assert ((got == 0) == (stack == 0).all(axis=0)).all()


@given(st.integers(1, 5), st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_eq6_max_pool_on_random_sparse_stacks(n_layers: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    stack = rng.integers(-MAX_STATE, MAX_STATE + 1, size=(n_layers, 9, 7)).astype(np.int16)
    stack[rng.random(stack.shape) < 0.5] = 0
    np.testing.assert_array_equal(logodds.fuse_max(stack), _max_over_observed(stack))
    # a strided view (a sampled stack's chosen layers) gives the same
    wide = np.zeros((n_layers, 9, 14), dtype=np.int16)
    wide[:, :, ::2] = stack
    np.testing.assert_array_equal(logodds.fuse_max(wide[:, :, ::2]), _max_over_observed(stack))


def test_eq6_max_pool_of_two_robots_layers_that_do_not_overlap() -> None:
    # Each robot's layer saw its own half (free with one wall cell); the other half is
    # unknown in it.  Both halves are free in the pooled map and both walls occupied.
    free, wall = logodds.prob_to_fixed([0.1, 0.95])
    a = np.zeros((4, 8), dtype=np.int16)
    b = np.zeros((4, 8), dtype=np.int16)
    a[:, :4], b[:, 4:] = free, free
    a[1, 1], b[2, 6] = wall, wall
    pooled = logodds.fuse_max(np.stack([a, b]))
    assert (pooled < 0).sum() == 30 and (pooled > 0).sum() == 2
    assert pooled[1, 1] == wall and pooled[2, 6] == wall
    # occupied where any observer says occupied, over another layer's free
    b[1, 1] = free
    assert logodds.fuse_max(np.stack([a, b]))[1, 1] == wall


def test_weightless_age_is_where_decay_leaves_no_unit() -> None:
    h = 10.0
    hi = logodds.clamp_limits(0.001)[1]
    age = logodds.weightless_age(h, hi)
    assert age == pytest.approx(h * math.log2(hi))
    assert 12.0 * h < age < 13.0 * h  # 6907 units: 12.75 half-lives
    cells = np.array([-hi, -1, 1, hi], dtype=np.float64)
    assert (np.trunc(cells * 0.5 ** ((age * 1.0001) / h)) == 0).all()
    assert np.trunc(hi * 0.5 ** ((age * 0.999) / h)) == 1  # just before: one unit is left
    with pytest.raises(ValueError):
        logodds.weightless_age(0.0, hi)


# -- Eq. 1 ---------------------------------------------------------------------------------


def test_eq1_update_is_an_odds_product() -> None:
    rng = np.random.default_rng(1)
    eps0 = 0.001
    lo, hi = logodds.clamp_limits(eps0)
    n_updates = 4
    # moderate ISMs so that the product stays inside the clamp (the clamp is tested below)
    isms = rng.uniform(0.3, 0.7, size=(n_updates, 25, 25))
    prior = rng.uniform(0.2, 0.8, size=(25, 25))
    state = logodds.prob_to_fixed(prior, eps0)
    for ism in isms:
        logodds.bayes_update(state, logodds.prob_to_fixed(ism, eps0), (lo, hi))
    # Eq. 1: Odd^-1(prod_t Odd(P_t)), the prior included as the first factor
    expected = prob_of_odds(odds(prior) * np.prod(odds(isms), axis=0))
    got = logodds.fixed_to_prob(state).astype(np.float64)
    np.testing.assert_array_less(np.abs(got - expected),
                                 dp_tol(expected, (n_updates + 1) * HALF_UNIT))


def test_eq1_update_clamps_to_eps0() -> None:
    eps0 = 0.01
    limits = logodds.clamp_limits(eps0)
    state = np.zeros(3, dtype=np.int16)
    inc = logodds.prob_to_fixed(np.array([0.9, 0.1, 0.5]), eps0)
    for _ in range(10):  # odds 9^10 would be P = 1 - 3e-10 without the clamp
        logodds.bayes_update(state, inc, limits)
    p = logodds.fixed_to_prob(state)
    np.testing.assert_allclose(p, [1 - eps0, eps0, 0.5], atol=dp_tol(0.01, HALF_UNIT))


def test_clamp_limits_are_logit_of_eps0() -> None:
    for eps0 in (MIN_EPS0, 1e-4, 0.001, 0.1, 0.49):
        lo, hi = logodds.clamp_limits(eps0)
        assert lo == -hi
        assert abs(hi / SCALE - math.log((1 - eps0) / eps0)) <= HALF_UNIT
        assert hi <= MAX_STATE
    for bad in (0.0, MIN_EPS0 / 2, 0.5, 0.7, -0.1, float("nan")):
        with pytest.raises(ValueError):
            logodds.clamp_limits(bad)


def test_unknown_ism_cells_are_a_no_op() -> None:
    rng = np.random.default_rng(2)
    eps0 = 0.001
    limits = logodds.clamp_limits(eps0)
    state = rng.integers(limits[0], limits[1] + 1, size=(16, 16)).astype(np.int16)
    before = state.copy()
    occ = np.full((16, 16), -1, dtype=np.int8)
    logodds.bayes_update(state, logodds.increments(occ, Encoding.OCCUPANCY_I8, eps0), limits)
    np.testing.assert_array_equal(state, before)
    # P = 0.5 is exactly representable in float32 (and occupancy 50 is exactly 50 %)
    half = np.full((16, 16), 0.5, dtype=np.float32)
    logodds.bayes_update(state, logodds.increments(half, Encoding.PROB_F32, eps0), limits)
    fifty = np.full((16, 16), 50, dtype=np.int8)
    logodds.bayes_update(state, logodds.increments(fifty, Encoding.OCCUPANCY_I8, eps0), limits)
    np.testing.assert_array_equal(state, before)
    # a mixed ISM touches exactly its known cells
    mixed = np.where(rng.random((16, 16)) < 0.5, -1, 90).astype(np.int8)
    logodds.bayes_update(state, logodds.increments(mixed, Encoding.OCCUPANCY_I8, eps0), limits)
    unknown = mixed == -1
    np.testing.assert_array_equal(state[unknown], before[unknown])
    known = ~unknown
    assert ((state[known] > before[known]) | (before[known] == limits[1])).all()


def test_increments_accept_plain_integer_arrays() -> None:
    # Codes given as a default-int array (not int8/uint8) still mean one increment per cell.
    codes = np.array([[100, -1, 0]])
    inc = logodds.increments(codes, Encoding.OCCUPANCY_I8)
    assert inc.shape == (1, 3)
    assert inc[0, 0] > 0 and inc[0, 1] == 0 and inc[0, 2] < 0
    inc = logodds.increments(np.array([255, 0]), Encoding.PROB_U8)
    assert inc.shape == (2,) and inc[0] > 0 > inc[1]


# -- Clamp and overflow under arbitrary input ----------------------------------------------

fixed_incs = st.integers(-MAX_STATE, MAX_STATE) | st.sampled_from([-MAX_STATE, MAX_STATE, 0])
f32_probs = st.floats(0.0, 1.0, width=32) | st.sampled_from([0.0, 1.0, 0.5])


@st.composite
def increment_arrays(draw: st.DrawFn, eps0: float) -> np.ndarray:
    """Increments as the pipeline produces them, from any encoding and any valid data."""
    kind = draw(st.sampled_from(["fixed", "occupancy_i8", "prob_u8", "prob_f32", "nats"]))
    n = 6
    if kind == "fixed":
        return np.array(draw(st.lists(fixed_incs, min_size=n, max_size=n)), dtype=np.int16)
    if kind == "occupancy_i8":
        codes = draw(st.lists(st.integers(-1, 100), min_size=n, max_size=n))
        return logodds.increments(np.array(codes, np.int8), kind, eps0)
    if kind == "prob_u8":
        codes = draw(st.lists(st.integers(0, 255), min_size=n, max_size=n))
        return logodds.increments(np.array(codes, np.uint8), kind, eps0)
    if kind == "prob_f32":
        ps = draw(st.lists(f32_probs, min_size=n, max_size=n))
        return logodds.increments(np.array(ps, np.float32), kind, eps0)
    nats = draw(st.lists(st.floats(allow_nan=False), min_size=n, max_size=n))
    return logodds.to_fixed(np.array(nats))  # includes +-inf and +-1e308


@settings(max_examples=150, deadline=None, derandomize=True)
@given(data=st.data(), eps0=eps0s)
def test_clamp_holds_and_int16_never_overflows(data: st.DataObject, eps0: float) -> None:
    limits = logodds.clamp_limits(eps0)
    lo, hi = limits
    state = np.array(data.draw(st.lists(st.integers(lo, hi), min_size=6, max_size=6)),
                     dtype=np.int16)
    exact = state.astype(np.int64)
    for _ in range(data.draw(st.integers(1, 12))):
        inc = data.draw(increment_arrays(eps0))
        assert inc.dtype == np.int16
        assert (np.abs(inc.astype(np.int64)) <= MAX_STATE).all()
        logodds.bayes_update(state, inc, limits)
        exact = np.clip(exact + inc.astype(np.int64), lo, hi)  # int64: cannot overflow
        assert state.dtype == np.int16
        np.testing.assert_array_equal(state, exact)
        assert (state >= lo).all() and (state <= hi).all()


# -- LUTs ----------------------------------------------------------------------------------


@pytest.mark.parametrize("eps0", [MIN_EPS0, 0.001, 0.05])
def test_occupancy_lut_is_logit_of_decoded_probability(eps0: float) -> None:
    lut = logodds.increment_lut(Encoding.OCCUPANCY_I8, eps0)
    assert lut.shape == (256,) and lut.dtype == np.int16
    for code in range(-128, 128):
        entry = int(lut[code & 0xFF])
        if 0 <= code <= 100:
            p = logodds.decode_to_prob(np.array([code], np.int8), Encoding.OCCUPANCY_I8)[0]
            p = min(max(float(p), eps0), 1 - eps0)
            assert abs(entry / SCALE - math.log(p / (1 - p))) <= HALF_UNIT + 1e-6, code
        else:  # -1 unknown; the rest invalid (the codec rejects them): no information
            assert entry == 0, code


@pytest.mark.parametrize("eps0", [MIN_EPS0, 0.001, 0.05])
def test_prob_u8_lut_is_logit_of_decoded_probability(eps0: float) -> None:
    lut = logodds.increment_lut(Encoding.PROB_U8, eps0)
    assert lut.shape == (256,) and lut.dtype == np.int16
    codes = np.arange(256, dtype=np.uint8)
    p = logodds.decode_to_prob(codes, Encoding.PROB_U8).astype(np.float64)
    p = np.clip(p, eps0, 1 - eps0)
    np.testing.assert_array_less(np.abs(lut / SCALE - np.log(p / (1 - p))), HALF_UNIT + 1e-6)
    assert (np.diff(lut.astype(np.int64)) >= 0).all()  # monotone in the code
    np.testing.assert_array_equal(logodds.increments(codes, Encoding.PROB_U8, eps0), lut)


def test_lut_is_read_only() -> None:
    lut = logodds.increment_lut(Encoding.PROB_U8)
    with pytest.raises(ValueError):
        lut[0] = 1


# -- forget --------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None, derandomize=True)
@given(values=st.lists(st.integers(-MAX_STATE, MAX_STATE), min_size=1, max_size=20),
       factor=st.floats(0.0, 1.0))
def test_forget_moves_toward_zero_and_never_crosses(values: list[int], factor: float) -> None:
    state = np.array(values, dtype=np.int16)
    before = state.astype(np.int64)
    logodds.forget(state, factor)
    after = state.astype(np.int64)
    assert state.dtype == np.int16
    assert (np.abs(after) <= np.abs(before)).all()
    assert (after * before >= 0).all()  # same sign or zero: never crosses unknown
    # and it is the multiplication it claims to be, within rounding
    assert (np.abs(after - before * factor) <= 0.5 + 1e-3 * np.abs(before)).all()


def test_forget_repeated_approaches_unknown() -> None:
    state = np.array([MAX_STATE, -MAX_STATE, 7000, -3, 0], dtype=np.int16)
    for _ in range(200):
        logodds.forget(state, 0.9)
    # rounding stops it where |l| * 0.1 < 0.5 units, i.e. within 5 units (0.005 nats) of 0
    assert (np.abs(state) < 5).all()
    logodds.forget(state, 0.0)
    assert (state == 0).all()
    for bad in (-0.1, 1.1, float("nan")):
        with pytest.raises(ValueError):
            logodds.forget(state, bad)


# -- encode / decode round trips -----------------------------------------------------------


@pytest.mark.parametrize("encoding", ["prob_f32", "prob_u8", "occupancy_i8", "logodds_i16"])
def test_encode_fixed_decode_to_prob_round_trip(encoding: str) -> None:
    rng = np.random.default_rng(7)
    lo, hi = logodds.clamp_limits(0.001)
    l = rng.integers(lo, hi + 1, size=(20, 20)).astype(np.int16)
    l[0, :5] = [0, lo, hi, 1, -1]
    expected = 1.0 / (1.0 + np.exp(-l / SCALE))
    enc = logodds.encode_fixed(l, encoding)
    assert enc.dtype == logodds.ENCODING_DTYPES[Encoding(encoding)]
    got = logodds.decode_to_prob(enc, encoding)
    tol = {"prob_f32": 2 * F32, "logodds_i16": 2 * F32, "prob_u8": 0.5 / 255 + 1e-6,
           "occupancy_i8": 0.5 / 100 + 1e-6}[encoding]
    np.testing.assert_array_less(np.abs(got - expected), tol)
    if encoding == "occupancy_i8":
        assert enc[0, 0] == logodds.OCCUPANCY_UNKNOWN  # l == 0 is exactly unknown
        assert got[0, 0] == 0.5
    if encoding == "logodds_i16":
        np.testing.assert_array_equal(enc, l)


@pytest.mark.parametrize("encoding", ["prob_u8", "occupancy_i8"])
def test_every_8bit_code_round_trips_through_the_map(encoding: str) -> None:
    """code -> probability -> fixed log-odds -> code gives the code back (50 % -> unknown)."""
    dtype = logodds.ENCODING_DTYPES[Encoding(encoding)]
    codes = (np.arange(256, dtype=np.uint8) if encoding == "prob_u8"
             else np.arange(-1, 101).astype(np.int8))
    p = logodds.decode_to_prob(codes, encoding)
    back = logodds.encode_fixed(logodds.prob_to_fixed(p, 0.001), encoding)
    assert back.dtype == dtype
    expected = codes.copy()
    if encoding == "occupancy_i8":
        expected[codes == 50] = logodds.OCCUPANCY_UNKNOWN  # P = 0.5 is written as unknown
    np.testing.assert_array_equal(back, expected)


def test_fuse_results_encode_beyond_int16() -> None:
    fused = np.array([40000, -40000, 5], dtype=np.int32)  # sums of several layers
    np.testing.assert_array_equal(logodds.encode_fixed(fused, "logodds_i16"),
                                  [32767, -32767, 5])
    np.testing.assert_array_equal(logodds.encode_fixed(fused, "prob_u8"), [255, 0, 128])


def test_logit_sigmoid_and_fixed_conversions() -> None:
    p = np.array([1e-6, 0.1, 0.5, 0.9, 1 - 1e-6])
    np.testing.assert_allclose(logodds.sigmoid(logodds.logit(p)), p, rtol=1e-9)
    assert logodds.logit(0.5) == 0.0 and logodds.sigmoid(0.0) == 0.5
    np.testing.assert_array_equal(logodds.to_fixed([1e300, -np.inf, 1.2344, -1.2346]),
                                  [MAX_STATE, -MAX_STATE, 1234, -1235])
    np.testing.assert_allclose(logodds.from_fixed(np.array([1500, -250])), [1.5, -0.25])


@pytest.mark.parametrize("encoding", ["prob_u8", "prob_f32", "occupancy_i8"])
def test_table_encoding_equals_the_definition_for_every_int16(encoding: str) -> None:
    every = np.arange(-32768, 32768, dtype=np.int32)
    p = logodds.sigmoid(every / logodds.SCALE)
    want = {"prob_f32": p.astype(np.float32),
            "prob_u8": np.rint(p.astype(np.float32) * 255.0).astype(np.uint8),
            "occupancy_i8": np.where(every == 0, -1,
                                     np.rint(p.astype(np.float32) * 100.0)).astype(np.int8)}
    got16 = logodds.encode_fixed(every.astype(np.int16), encoding)
    np.testing.assert_array_equal(got16, want[encoding])
    # Eq. 6 sums beyond int16 encode like the int16 extremes.
    beyond = logodds.encode_fixed(np.array([-10**6, 10**6], np.int32), encoding)
    np.testing.assert_array_equal(beyond, want[encoding][[0, -1]])


@pytest.mark.parametrize("shape", [(3,), (4,), (1, 1), (1, 4), (4, 1), (2, 2), (7, 3), (2, 3, 4)])
def test_bayes_update_matches_the_reference_for_any_layout(shape: tuple[int, ...]) -> None:
    # The 2-D fast path goes through OpenCV, which reads short 1-D arrays as scalars and
    # refuses some strided outputs: every layout must still give clamp(state + inc).
    rng = np.random.default_rng(sum(shape))
    limits = logodds.clamp_limits()
    big_state = rng.integers(-6900, 6900, (9, *shape)).astype(np.int16)
    big_inc = rng.integers(-6000, 6000, (9, *shape)).astype(np.int16)
    for view in (np.s_[0], np.s_[1::3]):  # contiguous, then strided along the first axis
        state, inc = big_state[view], big_inc[view]
        expected = np.clip(state.astype(np.int32) + inc, *limits).astype(np.int16)
        logodds.bayes_update(state, inc, limits)
        np.testing.assert_array_equal(big_state[view], expected)
    cols = big_state[0].reshape(-1)[::2]  # a strided 1-D view
    inc1 = big_inc[0].reshape(-1)[::2]
    expected = np.clip(cols.astype(np.int32) + inc1, *limits).astype(np.int16)
    logodds.bayes_update(cols, inc1, limits)
    np.testing.assert_array_equal(big_state[0].reshape(-1)[::2], expected)


def test_bayes_update_on_column_strided_views() -> None:
    rng = np.random.default_rng(9)
    limits = logodds.clamp_limits()
    state = rng.integers(-6900, 6900, (20, 30)).astype(np.int16)
    inc = rng.integers(-6000, 6000, (20, 30)).astype(np.int16)
    expected = state.copy()
    expected[2:9, 3:20:3] = np.clip(state[2:9, 3:20:3] + inc[1:8, 0:17:3].astype(np.int32),
                                    *limits)
    logodds.bayes_update(state[2:9, 3:20:3], inc[1:8, 0:17:3], limits)
    np.testing.assert_array_equal(state, expected)


# -- value encodings ------------------------------------------------------------------------
# An exact "no information" in 8-bit and float ISMs: ``prob_u8`` keeps its meaning (p = v / 255,
# no exact unknown); ``prob_u8_v2`` is 0..254 -> p = v / 254 (127 exactly 0.5) and 255 = unknown;
# ``prob_f32`` takes NaN as unknown.  Expected increments are computed here from the definitions
# (``math.log``), not from the project's LUTs.
EPS0 = logodds.DEFAULT_EPS0
LO, HI = logodds.clamp_limits(EPS0)


def fixed(p: float) -> int:
    """round(1000 * logit(clip(p, eps0, 1 - eps0))), from the definition."""
    q = min(max(p, EPS0), 1.0 - EPS0)
    return round(1000.0 * math.log(q / (1.0 - q)))


def test_prob_u8_v2_table_from_its_definition() -> None:
    lut = logodds.increment_lut("prob_u8_v2")
    want = [fixed(v / 254.0) for v in range(255)] + [0]
    assert lut.tolist() == want
    assert lut[127] == 0 and lut[255] == 0  # exactly no information, twice
    assert (lut[0], lut[254]) == (LO, HI)  # the clamp ends, as prob_u8's 0 and 255
    assert lut[128] == fixed(128 / 254) == 16  # one step above unknown: log(128 / 126)
    # symmetric about 127: v and 254 - v are opposite evidence
    assert (lut[:127] == -lut[254:127:-1]).all()


def test_prob_u8_keeps_its_meaning_for_robots_already_deployed() -> None:
    lut = logodds.increment_lut("prob_u8")
    assert lut.tolist() == [fixed(v / 255.0) for v in range(256)]
    assert (lut[0], lut[127], lut[128], lut[255]) == (LO, -8, 8, HI)


def test_prob_f32_nan_cells_are_untouched_and_the_rest_fused() -> None:
    p = np.array([[np.nan, 0.9], [0.1, np.nan]], np.float32)
    inc = logodds.increments(p, "prob_f32")
    assert inc.tolist() == [[0, fixed(float(np.float32(0.9)))], [fixed(float(np.float32(0.1))), 0]]


def test_prob_u8_v2_as_a_reply_encoding() -> None:
    l = np.array([0, LO, HI, 1, -1, 2000], np.int16)
    enc = logodds.encode_fixed(l, "prob_u8_v2")
    assert enc.dtype == np.uint8
    p2000 = 1.0 / (1.0 + math.exp(-2.0))
    assert enc.tolist() == [255, 0, 254, 127, 127, round(p2000 * 254)]
    dec = logodds.decode_to_prob(enc, "prob_u8_v2")
    assert dec[0] == 0.5 and dec[3] == 0.5 and dec[2] == 1.0
    # Every code round-trips through the map (127, p = 0.5, is written as 255: unknown).
    codes = np.arange(256, dtype=np.uint8)
    back = logodds.encode_fixed(logodds.prob_to_fixed(logodds.decode_to_prob(codes,
                                                                             "prob_u8_v2")),
                                "prob_u8_v2")
    want = codes.copy()
    want[127] = 255
    np.testing.assert_array_equal(back, want)
