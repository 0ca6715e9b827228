"""The scene solver's compiled kernels against the plain numpy they replace: the noise model's
binned medians, a frame's normal equations and the conjugate gradients."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli.solve import frames, scenemodel


def _binned_medians(residuals, level, bins=8):
    """The noise model's medians as first written: one boolean mask per quantile bin of the level (the
    quantiles of every m-th level, m the levels over ``EDGE_SAMPLES``)."""
    edges = np.quantile(level[:: max(1, level.size // scenemodel.EDGE_SAMPLES)], np.linspace(0, 1, bins + 1))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, bins - 1)
    out = []
    for b in range(bins):
        if (which == b).sum() >= 8:
            out.append((np.median(level[which == b]), np.median(residuals[which == b] ** 2)))
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), step=st.sampled_from([0.0, 0.05, 0.5]), dark=st.floats(0.0, 0.9),
       size=st.sampled_from([5000, 150_001]))
def test_noise_model_bins_are_those_of_plain_masks(seed, step, dark, size):
    # levels with ties (rounded to ``step``) and a share at exactly 0 (black), so bins can be empty;
    # 150 001 levels take their edges from every 4th, so some fall below the first or above the last
    rng = np.random.default_rng(seed)
    level = rng.gamma(2.0, 0.5, size)
    if step:
        level = np.round(level / step) * step
    level[: int(dark * level.size)] = 0.0
    residuals = rng.standard_normal(level.size) * np.sqrt(1e-3 + 1e-2 * level)
    seen = []
    with pytest.MonkeyPatch.context() as patch:  # the line fitted to the medians: what it is given
        patch.setattr(scenemodel.np, "polyfit", lambda x, y, deg: seen.append(list(zip(x, y))) or (0.0, 1.0))
        scenemodel.noise_variance(residuals, level)
    expected = [(lv, sq / scenemodel.CHI2_MEDIAN) for lv, sq in _binned_medians(residuals, level)]
    if len(expected) >= 2 and np.ptp([lv for lv, _ in expected]) > 0:
        assert seen == [expected]  # bit for bit
    else:
        assert seen == []


def test_normal_equations_are_those_of_the_jacobian():
    rng = np.random.default_rng(1)
    n = 3000
    u, v = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    ax, ay, ap, residual = (rng.standard_normal(n) for _ in range(4))
    weight = rng.uniform(0.0, 2.0, n) * (rng.random(n) > 0.2)
    basis = np.stack([np.ones(n), u, v, u * u, u * v, v * v], axis=1)
    J = np.concatenate([ax[:, None] * basis, ay[:, None] * basis, ap[:, None]], axis=1)
    H, g = np.zeros((13, 13)), np.zeros(13)
    unused = weight == 0  # a reading not used may have no slope: it must not reach the sums
    with np.errstate(invalid="ignore"):
        frames._normal_equations(np.where(unused, np.nan, ax), np.where(unused, np.inf, ay), ap, weight, residual, u,
                                 v, H, g)
    np.testing.assert_allclose(H, J.T @ (weight[:, None] * J), rtol=1e-12, atol=1e-12 * np.abs(H).max())
    np.testing.assert_allclose(g, J.T @ (weight * residual), rtol=1e-12, atol=1e-12 * np.abs(g).max())


@pytest.mark.parametrize("iterations", [5, 200])
def test_conjugate_gradients_follow_the_textbook(iterations):
    # against the same recurrence in plain numpy: equal to rounding at any cap, the solution at convergence
    rng = np.random.default_rng(2)
    M = rng.standard_normal((60, 60))
    A = M @ M.T + 60 * np.eye(60)
    b, d = rng.standard_normal(60), np.diag(A).copy()
    (x,), used = scenemodel._pcg_path(lambda p: A @ p, b, d, (iterations,), 1e-10)
    ref, r = np.zeros(60), b.copy()
    z = r / d
    p, rz = z.copy(), r @ z
    for _ in range(min(iterations, used)):
        q = A @ p
        alpha = rz / (p @ q)
        ref += alpha * p
        r -= alpha * q
        z = r / d
        rz, previous = r @ z, rz
        p = z + rz / previous * p
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-12)
    if iterations == 200:
        assert used < 200
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-8)


def test_conjugate_gradients_path_holds_the_iterates_at_its_stops():
    # each stop's iterate is the solve capped there, bit for bit; stops after convergence get the solution
    rng = np.random.default_rng(3)
    M = rng.standard_normal((60, 60))
    A = M @ M.T + 60 * np.eye(60)
    b, d = rng.standard_normal(60), np.diag(A).copy()
    path, used = scenemodel._pcg_path(lambda p: A @ p, b, d, (3, 7, 7, 12), 1e-10)
    assert used == 12 and len(path) == 4
    for stop, x in zip((3, 7, 7, 12), path):
        np.testing.assert_array_equal(x, scenemodel._pcg_path(lambda p: A @ p, b, d, (stop,), 1e-10)[0][0])
    path, used = scenemodel._pcg_path(lambda p: A @ p, b, d, (2, 150, 200), 1e-10)
    assert used < 150
    np.testing.assert_array_equal(path[1], path[2])
    np.testing.assert_allclose(path[2], np.linalg.solve(A, b), rtol=1e-8)
