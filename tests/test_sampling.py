"""The scene solver's sampling operator (solve/sampling.py): the box of a linear spline, the rows it
makes, and its compiled products against the same operator as a sparse matrix."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli.solve.sampling import box_spline_weights, sampling


def test_box_of_a_linear_spline_known_answer():
    # mean of the hat over [-1/2, 1/2] is 3/4, over [1/2, 1] (either neighbour) 1/8
    taps, weights = box_spline_weights(np.array([5.0]), 1.0)
    kept = weights[0] > 0
    assert list(taps[0][kept]) == [4, 5, 6]
    np.testing.assert_allclose(weights[0][kept], [0.125, 0.75, 0.125])


@settings(max_examples=50, deadline=None)
@given(u=st.floats(-50, 50), width=st.floats(0.25, 4.0))
def test_box_weights_keep_constants_and_linear_functions(u, width):
    # the box mean of a linear function is its value at the centre: the weights are a partition of
    # unity with first moment u
    taps, weights = box_spline_weights(np.array([u]), width)
    assert weights.min() >= 0
    assert weights.sum() == pytest.approx(1.0, abs=1e-12)
    assert (weights * taps).sum() == pytest.approx(u, abs=1e-9)


def test_observation_rows_average_the_scene_inside_and_are_empty_outside():
    points = np.array([[3.2, 4.7], [0.0, 0.0], [-3.0, 5.0]])  # (x, y) grid px
    A, inside = sampling([points], (20, 20), 2, 1.0)
    A = A.sparse()
    assert list(inside) == [True, False, False]  # the second's box reaches past the first sample
    np.testing.assert_allclose(A @ np.ones(400), [1.0, 0.0, 0.0], atol=1e-12)
    ramp = np.tile(np.arange(20.0), 20)  # scene value = fine column index = 2 x + 1/2
    assert (A @ ramp)[0] == pytest.approx(2 * 3.2 + 0.5)


@settings(max_examples=30, deadline=None)
@given(scale=st.integers(1, 4), aperture=st.sampled_from([1.0, 0.5]), seed=st.integers(0, 2**16))
def test_compiled_products_are_those_of_the_sparse_matrix(scale, aperture, seed):
    # every support the loops are written for (3 and 4 samples a side) and a wider one (CSR), with
    # readings out of view (zero rows) and at the grid's last samples
    rng = np.random.default_rng(seed)
    h, w = 7, 9
    fine = (scale * h, scale * w)
    points = [np.column_stack([rng.uniform(-1.5, w + 0.5, 40), rng.uniform(-1.5, h + 0.5, 40)]) for _ in range(3)]
    A, inside = sampling(points, fine, scale, aperture)
    assert inside.any() and not inside.all()
    M = A.sparse().astype(np.float64)
    v, r = rng.standard_normal(fine[0] * fine[1]), rng.standard_normal(A.shape[0])
    # float32 weights and sums: a few float32 ulps of the sums' terms
    np.testing.assert_allclose(A.forward(v), M @ v.astype(np.float32), atol=1e-5 * np.abs(v).max())
    np.testing.assert_allclose(A.back(r), M.T @ r.astype(np.float32), atol=1e-5 * np.abs(r).max())
    np.testing.assert_allclose(A.back_squared(r), M.multiply(M).T @ r.astype(np.float32),
                               atol=1e-5 * np.abs(r).max())
    assert not A.forward(v)[~inside].any()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), width=st.sampled_from([0.5, 1.0, 1.5, 2.0, 3.0, 4.0]))
def test_compiled_weights_are_box_spline_weights_bit_for_bit(seed, width):
    from gainfpn_cli.solve.sampling import _box_weights

    u = np.random.default_rng(seed).uniform(-20.0, 600.0, 500)
    u[:3] = [0.0, 1.5, -0.25]  # on a tap and half-way
    taps, weights = box_spline_weights(u, width)
    first, compiled = np.empty(u.size, np.int64), np.empty(weights.shape, np.float32)
    _box_weights(u, width, first, compiled)
    np.testing.assert_array_equal(first, taps[:, 0])
    np.testing.assert_array_equal(compiled, weights.astype(np.float32))
