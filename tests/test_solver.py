import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from gainfpn_cli.errors import EstimationError
from gainfpn_cli.solve.kkt import OK, REGULARISED, UNESTIMATED, _solve_gauged, solve_block

# docs/method.md section 2, paper Fig. 2: integer displacements, n_B = 4, F = 2, n_R = 6
I0 = [131.1, 153, 135, 97]
I1 = [140.76, 162, 121.25, 95]
I2 = [149.04, 145.5, 118.75, 103]
K_STAR = [1.0503, 0.9782, 0.9239, 1.0286, 1.0503, 0.9687]


def _shift(n_b, n_r, s):
    T = np.zeros((n_b, n_r))
    T[np.arange(n_b), np.arange(n_b) + s] = 1.0
    return T


def test_reference_example_to_four_decimals():
    k = solve_block(I0, [I1, I2], [_shift(4, 6, 1), _shift(4, 6, 2)])
    np.testing.assert_allclose(k, K_STAR, atol=5e-5)
    assert k.sum() == pytest.approx(6.0, abs=1e-12)
    # corrected block is the ideal (138, 150, 125, 100) up to one common factor
    np.testing.assert_allclose(np.array(I0) * k[:4] / [138, 150, 125, 100], 0.998, atol=1e-3)


def test_sparse_and_dense_T_agree():
    dense = solve_block(I0, [I1, I2], [_shift(4, 6, 1), _shift(4, 6, 2)])
    sparse = solve_block(I0, [I1, I2], [sp.csr_matrix(_shift(4, 6, 1)), sp.csr_matrix(_shift(4, 6, 2))])
    np.testing.assert_array_equal(dense, sparse)


def _kkt(i0, it, T, lam):
    """Independent oracle: the full KKT system of eq. 6, for numpy.linalg."""
    n_b, n_r = T[0].shape
    A = np.vstack([np.hstack([np.diag(i0), np.zeros((n_b, n_r - n_b))]) - np.diag(row) @ t for row, t in zip(it, T)])
    Q = A.T @ A
    K = np.block([[2 * (Q + lam * np.eye(n_r)), np.ones((n_r, 1))], [np.ones((1, n_r)), np.zeros((1, 1))]])
    rhs = np.concatenate([2 * lam * np.ones(n_r), [n_r]])
    return K, rhs


def _bilinear_rows(rng, n_b, n_r, shift):
    """Rows of T for non-integer displacements: 4 bilinear weights in a 1-D chain of pixels."""
    T = np.zeros((n_b, n_r))
    for m in range(n_b):
        fx, fy = rng.uniform(0.05, 0.95, size=2)
        cols = [(m + shift) % n_r, (m + shift + 1) % n_r, (m + shift + 2) % n_r, (m + shift + 3) % n_r]
        for c, w in zip(cols, [(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]):
            T[m, c] += w
    return T


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 12), st.integers(1, 5), st.sampled_from([0.0, 1e-3, 0.5, 50.0]))
def test_block_solver_matches_dense_kkt_oracle(seed, n_b, n_frames, lam):
    rng = np.random.default_rng(seed)
    n_r = n_b + 3
    i0 = rng.uniform(20, 250, n_b)
    it = rng.uniform(20, 250, (n_frames, n_b))
    T = [_bilinear_rows(rng, n_b, n_r, shift=rng.integers(1, 3)) for _ in range(n_frames)]
    K, rhs = _kkt(i0, it, T, lam)
    cond = np.linalg.cond(K)
    assume(cond < 1e10)  # a singular system has no oracle answer to compare with
    oracle = np.linalg.solve(K, rhs)[:n_r]
    k = solve_block(i0, it, T, lam=lam)
    # two exact methods for one quadratic: they differ by rounding amplified by the condition number
    np.testing.assert_allclose(k, oracle, rtol=0, atol=1e-14 * cond)
    assert k.sum() == pytest.approx(n_r, abs=1e-9)


def test_true_gain_zeroes_the_residual_for_bilinear_weights():
    # system consistency: a flat scene seen by pixels of gain a; bilinear
    # interpolation of the *corrected* frame is exact there, so k = 1/a
    # (scaled to the gauge) solves eq. 6 with zero residual
    rng = np.random.default_rng(3)
    n_b, n_r, scene = 6, 10, 120.0
    a = rng.uniform(0.9, 1.1, n_r)
    T = [_bilinear_rows(rng, n_b, n_r, shift=s) for s in (1, 2, 3)]
    i0 = scene * a[:n_b]
    # eq. 5 compares k(p) i0(p) = scene with i~ * (T k); for k = 1/a that is
    # scene when i~ = scene / (T @ (1/a))
    it = [scene / (t @ (1 / a)) for t in T]
    k = solve_block(i0, it, T)
    expected = (1 / a) * n_r / np.sum(1 / a)
    np.testing.assert_allclose(k, expected, rtol=1e-9)


def test_singular_block_raises():
    # no frame-0 signal at all: every k gives zero residual
    with pytest.raises(EstimationError, match="singular"):
        solve_block([0.0, 0.0], [[0.0, 0.0]], [np.eye(2)])


def test_huge_lambda_pulls_k_to_one_and_tiny_lambda_changes_nothing():
    T = [_shift(4, 6, 1), _shift(4, 6, 2)]
    np.testing.assert_allclose(solve_block(I0, [I1, I2], T, lam=1e12), 1.0, atol=1e-6)
    np.testing.assert_allclose(solve_block(I0, [I1, I2], T, lam=1e-12), K_STAR, atol=5e-5)


@pytest.mark.parametrize("bad, message", [
    (dict(i0=[[1.0]]), "i0 must have shape"),
    (dict(it=[1.0, 2.0]), "it must have shape"),
    (dict(T=[np.eye(4)]), "one matrix per frame"),
    (dict(T=[np.eye(3, 6), np.eye(3, 6)]), "shape"),
    (dict(lam=-1.0), "lam must be"),
])
def test_solve_block_validates(bad, message):
    args = dict(i0=I0, it=[I1, I2], T=[_shift(4, 6, 1), _shift(4, 6, 2)], lam=0.0) | bad
    with pytest.raises(ValueError, match=message):
        solve_block(args["i0"], args["it"], args["T"], lam=args["lam"])


def test_gauged_solver_statuses():
    # well conditioned: OK; singular with a safety limit: REGULARISED toward 1;
    # a single unknown carries no relative information: UNESTIMATED
    Q = np.diag([1.0, 2.0, 3.0])
    assert _solve_gauged(Q, lam=0.0, max_condition=1e4)[1] == OK
    singular = np.zeros((3, 3))
    singular[0, 0] = 1.0
    k, status, _ = _solve_gauged(singular, lam=0.0, max_condition=1e4)
    assert status == REGULARISED and np.all(np.isfinite(k)) and k.sum() == pytest.approx(3.0)
    assert _solve_gauged(np.ones((1, 1)), lam=0.0, max_condition=1e4)[1] == UNESTIMATED
    # out of the physical range even after regularising: UNESTIMATED, k = 1
    k, status, _ = _solve_gauged(Q, lam=0.0, max_condition=1e4, k_range=(0.99, 1.01))
    assert status in (REGULARISED, UNESTIMATED)
    assert np.all((k >= 0.99) & (k <= 1.01))


def test_sparse_path_agrees_with_dense():
    A = sp.random(40, 12, density=0.4, random_state=1) + sp.eye(40, 12)
    Q = (A.T @ A).toarray()
    dense = _solve_gauged(Q, lam=0.1, max_condition=1e12)
    sparse = _solve_gauged(sp.csc_matrix(Q), lam=0.1, max_condition=1e12)
    np.testing.assert_allclose(dense[0], sparse[0], rtol=1e-9)
