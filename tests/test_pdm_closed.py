"""PDM-Closed building blocks: IDM step, shared leading-agent buffer, path interpolation, AVX-512 arctan2."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import interp1d

from scorer.geometry import (
    _MAIN_PATH_HIGH,
    _MAIN_PATH_LOW,
    _SVML_PROBE_ARCTAN2,
    _SVML_PROBE_X,
    _SVML_PROBE_Y,
    _fused_multiply_add,
    _fused_multiply_add_float,
    _svml_arctan2_float,
    normalize_angle,
    svml_arctan2_emulated,
)
from scorer.pdm_closed import (
    EGO_LENGTH,
    PdmPath,
    _shared_buffer,
    idm_step,
    idm_target_speeds,
    interpolate_paths,
    parallel_poses,
)

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
# Dekker's exact product needs the product's low part to be representable: no subnormal results.
# Map coordinates and angles never come near 1e-100, so the emulation's domain excludes them.
normal = finite.filter(lambda v: v == 0.0 or abs(v) >= 1e-100)


def test_target_speeds_are_fractions_of_the_limit_or_of_15_mps() -> None:
    assert idm_target_speeds(10.0).tolist() == [0.2 * 10.0, 0.4 * 10.0, 0.6 * 10.0, 0.8 * 10.0, 10.0]
    assert idm_target_speeds(None).tolist() == [3.0, 6.0, 0.6 * 15.0, 12.0, 15.0]


def test_first_step_brakes_against_the_phantom_obstacle_then_accelerates() -> None:
    """Spec 9.4's example: v 10.0 -> 9.7 -> 9.84 (index 1 sees the unfilled leading buffer, index 2 free road)."""
    targets = np.array([15.0])
    progress, speed = idm_step(np.array([0.0]), np.array([10.0]), np.zeros((1, 3)), targets)
    assert (progress[0], speed[0]) == (1.0, 9.7)
    free_road = np.array([[1000.0, 0.0, EGO_LENGTH / 2]])
    progress, speed = idm_step(progress, speed, free_road, targets)
    assert progress[0] == 1.0 + 0.1 * 9.7
    assert abs(speed[0] - 9.84) < 0.01


def test_idm_never_brakes_harder_than_3_or_accelerates_more_than_1_5() -> None:
    speed = np.array([0.0, 5.0, 30.0])
    _, faster = idm_step(np.zeros(3), speed, np.tile([1e6, 0.0, 2.588], (3, 1)), np.array([10.0, 10.0, 10.0]))
    assert np.all(faster - speed <= 0.1 * 1.5 + 1e-12) and np.all(faster - speed >= -0.1 * 3.0 - 1e-12)


def test_shared_buffer_carries_the_previous_proposals_value_within_a_path_only() -> None:
    values = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    written = np.array([False, True, False, False, False, True])
    paths = np.array([0, 0, 0, 1, 1, 1])
    # Path 0: nothing before row 1, then row 1's value twice; path 1 starts from zeros again.
    assert _shared_buffer(values, written, paths).tolist() == [0.0, 2.0, 2.0, 0.0, 0.0, 6.0]


@settings(max_examples=100, deadline=None)
@given(
    steps=st.lists(st.floats(min_value=0.0, max_value=5.0), min_size=2, max_size=11),
    headings=st.lists(st.floats(min_value=-3.0, max_value=3.0), min_size=12, max_size=12),
    queries=st.lists(st.floats(min_value=-5.0, max_value=80.0), min_size=1, max_size=8),
)
def test_interpolation_is_scipy_interp1d_bit_for_bit(
    steps: list[float], headings: list[float], queries: list[float]
) -> None:
    x = np.cumsum([0.0, *steps])
    poses = np.column_stack([x, np.zeros_like(x), np.array(headings[: len(x)])])
    path = PdmPath.from_poses(poses)
    if path.length < 1e-5 or np.any(np.diff(path.progress) == 0):
        return  # scipy (as the devkit) divides by zero there; both give NaN, set to 0
    distances = np.array(queries)
    ours = interpolate_paths(
        path.states[None],
        path.progress[None],
        np.array([len(path.progress) - 1]),
        distances[None],
        normalize_angle,
    )[0]
    expected = interp1d(path.progress, path.states, axis=0)(np.clip(distances, 1e-5, path.length))
    expected[..., 2] = normalize_angle(expected[..., 2])
    assert np.array_equal(ours, expected)


def test_interpolation_unwraps_the_heading_across_pi() -> None:
    poses = np.array([[0.0, 0.0, 3.1], [1.0, 0.0, -3.1], [2.0, 0.0, -3.1]])
    path = PdmPath.from_poses(poses)
    middle = interpolate_paths(
        path.states[None], path.progress[None], np.array([2]), np.array([[0.5]]), normalize_angle
    )[0, 0]
    assert abs(abs(middle[2]) - math.pi) < 1e-9  # through pi, not through 0


def test_substring_keeps_the_vertices_in_range_else_cuts_the_line() -> None:
    path = PdmPath.from_poses(
        np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0], [30.0, 0.0, 0.0]])
    )
    assert shapely.get_coordinates(path.substring(5.0, 25.0)).tolist() == [[10.0, 0.0], [20.0, 0.0]]
    assert shapely.get_coordinates(path.substring(12.0, 18.0)).tolist() == [[12.0, 0.0], [18.0, 0.0]]
    assert shapely.get_coordinates(path.substring(-5.0, 99.0)).tolist()[-1] == [30.0, 0.0]


def test_parallel_poses_move_left_for_positive_offsets() -> None:
    moved = parallel_poses(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2]]), 1.0)
    assert np.allclose(moved, [[0.0, 1.0, 0.0], [-1.0, 0.0, math.pi / 2]], atol=1e-15)


@settings(max_examples=300, deadline=None)
@given(a=normal, b=normal, c=normal)
def test_emulated_fma_rounds_once(a: float, b: float, c: float) -> None:
    exact = Fraction(a) * Fraction(b) + Fraction(c)
    assert _fused_multiply_add(np.array([a]), np.array([b]), np.array([c]))[0] == float(exact)


@settings(max_examples=300, deadline=None)
@given(a=normal, b=normal, c=normal)
def test_emulated_fma_of_floats_rounds_once(a: float, b: float, c: float) -> None:
    assert _fused_multiply_add_float(a, b, c) == float(Fraction(a) * Fraction(b) + Fraction(c))


def test_both_emulated_fmas_round_to_odd_where_rounding_twice_would_tie() -> None:
    """a * b = 2^-53 + e (0 < e < 2^-106) and c = 1: the exact sum lies just above the midpoint between 1 and
    the next double, but its low part rounds to 2^-53, which ties back to 1 unless rounded to odd first."""
    a, b, c = 1 + 2**-52, 2**-53 * (1 - 2**-53), 1.0
    assert float(Fraction(a) * Fraction(b) + Fraction(c)) == 1 + 2**-52 and a * b + c == 1.0
    for sign in (1.0, -1.0):
        expected = sign * (1 + 2**-52)
        assert _fused_multiply_add(np.array([sign * a]), np.array([b]), np.array([sign * c]))[0] == expected
        assert _fused_multiply_add_float(sign * a, b, sign * c) == expected


def test_the_float_replays_main_path_is_svmls_high_word_test() -> None:
    """SVML takes its main path for 0x00300000 <= high word of |x| and |y| < 0x7E000000; the float replay
    compares values. On an AVX-512 host both paths give SVML's value, so only the bounds can be compared."""
    bounds = np.array([2.0**-1020, 2.0**993, 1.0, 5e-324, np.inf])
    values = np.concatenate([np.nextafter(bounds, 0.0), bounds, np.nextafter(bounds, np.inf), [np.nan]])
    high_word = values.view(np.uint64) >> np.uint64(32)
    svml = (high_word >= 0x00300000) & (high_word < 0x7E000000)
    ours = [bool(_MAIN_PATH_LOW <= value < _MAIN_PATH_HIGH) for value in values.tolist()]
    assert ours == svml.tolist() and 2 < sum(ours) < len(ours) - 2


def _hard_pairs() -> tuple[np.ndarray, np.ndarray]:
    """Return (y, x) pairs where the two replays could part: random over 12 orders of magnitude, on and one
    ulp beside every band limit, at the main path's bounds, and SVML's special values."""
    rng = np.random.default_rng(7)
    scale = 10.0 ** rng.uniform(-6, 6, size=(2, 100_000))
    y, x = rng.standard_normal((2, 100_000)) * scale
    limits = np.array([0.4375, 0.6875, 1.1875, 2.4375])
    along = rng.uniform(0.1, 100.0, size=(limits.size, 50))
    on_limits = (along * limits[:, None]).ravel()
    beside = np.concatenate([np.nextafter(on_limits, -np.inf), on_limits, np.nextafter(on_limits, np.inf)])
    bounds = np.array([2.0**-1020, 2.0**993])
    bound_values = np.concatenate([np.nextafter(bounds, 0.0), bounds, np.nextafter(bounds, np.inf)])
    special = np.array([0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, np.nan, 5e-324, 1e300, -2.5])
    edge_y = np.concatenate(
        [beside, np.tile(along.ravel(), 3), bound_values, np.repeat(special, special.size)]
    )
    edge_x = np.concatenate(
        [np.tile(along.ravel(), 3), beside, bound_values[::-1], np.tile(special, special.size)]
    )
    signs = rng.choice([-1.0, 1.0], size=(2, edge_y.size))
    return np.concatenate([y, edge_y * signs[0]]), np.concatenate([x, edge_x * signs[1]])


def test_the_float_replay_gives_the_numpy_replays_bits() -> None:
    y, x = _hard_pairs()
    with np.errstate(over="ignore"):
        replayed = svml_arctan2_emulated(y, x)  # more pairs than the float replay takes: numpy's
    floats = np.array([_svml_arctan2_float(a, b) for a, b in zip(y.tolist(), x.tolist(), strict=True)])
    assert np.array_equal(floats.view(np.int64), replayed.view(np.int64))


def test_a_few_pairs_take_the_float_replay_in_any_shape() -> None:
    y, x = _hard_pairs()
    replayed = svml_arctan2_emulated(y[:48], x[:48])
    for shape in [(), (1,), (2, 3), (16,)]:
        size = math.prod(shape)
        few = svml_arctan2_emulated(y[:size].reshape(shape), x[:size].reshape(shape))
        assert few.shape == shape and few.dtype == np.float64
        assert np.array_equal(few.ravel().view(np.int64), replayed[:size].view(np.int64))


# numpy's own arctan2 is SVML on AVX-512 hosts and libm elsewhere, so libm is read through `math`.
libm_arctan2 = np.vectorize(math.atan2, otypes=[np.float64])


def test_avx512_arctan2_differs_from_libm_by_at_most_one_ulp_and_keeps_special_values() -> None:
    rng = np.random.default_rng(0)
    y, x = rng.normal(size=200_000), rng.normal(size=200_000)
    ours, libm = svml_arctan2_emulated(y, x), libm_arctan2(y, x)
    assert np.all(np.abs(ours - libm) <= np.spacing(np.abs(libm)))
    assert 0.02 < np.mean(ours != libm) < 0.2  # SVML is not correctly rounded: about 7 % differ
    special_y = np.array([0.0, -0.0, 1.0, -1.0, 0.0, 2.0, np.inf, np.nan])
    special_x = np.array([1.0, -1.0, 0.0, -0.0, 0.0, np.inf, 1.0, 1.0])
    assert np.array_equal(
        svml_arctan2_emulated(special_y, special_x), np.arctan2(special_y, special_x), equal_nan=True
    )


def test_avx512_arctan2_gives_the_devkit_headings_where_libm_does_not() -> None:
    """Baseline segments of the reference maps and the heading the official cache stored for them."""
    segments = np.array(
        [
            [665407.312, 3996386.042, 665407.633, 3996386.17],
            [330928.065, 4691707.429, 330929.289, 4691708.997],
            [330955.016, 4691741.946, 330956.23, 4691743.501],
            [331027.146, 4691834.328, 331027.255, 4691834.467],
        ]
    )
    devkit = [0.37943168657386134, 0.9079894916263764, 0.9079303705665318, 0.9057809857221297]
    dy, dx = segments[:, 3] - segments[:, 1], segments[:, 2] - segments[:, 0]
    assert svml_arctan2_emulated(dy, dx).tolist() == devkit
    assert not np.any(libm_arctan2(dy, dx) == devkit)


def test_svml_probe_values_are_svml_and_not_libm() -> None:
    """The probe that tells whether numpy runs SVML: the emulation gives its values, libm does not."""
    assert np.array_equal(svml_arctan2_emulated(_SVML_PROBE_Y, _SVML_PROBE_X), _SVML_PROBE_ARCTAN2)
    assert not np.any(libm_arctan2(_SVML_PROBE_Y, _SVML_PROBE_X) == _SVML_PROBE_ARCTAN2)
