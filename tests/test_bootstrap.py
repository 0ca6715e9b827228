"""sigma_k's calibration on a synthetic burst's error (solve/bootstrap.py): the factor per tenth."""

import numpy as np
import pytest

from gainfpn_cli.solve.bootstrap import calibration


@pytest.mark.parametrize("scale, expected", [(1.6, 1.6), (0.5, 1.0)])
def test_each_tenth_is_scaled_to_the_error_it_has_and_never_down(scale, expected):
    # errors drawn with 1.6x (or half) the stated sigma in every tenth: the factors read 1.6 within the
    # sampling error of 10 000 draws a tenth (0.7 %), and a smaller error does not shrink sigma
    rng = np.random.default_rng(4)
    sigma = np.exp(rng.uniform(np.log(0.002), np.log(0.05), (200, 500)))
    error = scale * sigma * rng.standard_normal(sigma.shape)
    measured = calibration(sigma, error, np.ones(sigma.shape, bool))
    assert measured.prior is None and len(measured.factor) == 10
    np.testing.assert_allclose(measured.factor, expected, rtol=0.03)
    np.testing.assert_allclose(measured.sigma(np.float32(0.01)), 0.01 * expected, rtol=0.03)


def test_too_few_pixels_measure_nothing():
    sigma = np.full((50, 100), 0.01)  # 5000 pixels: 5 parts of 1000, fewer than the 6 a calibration needs
    assert calibration(sigma, sigma, np.ones(sigma.shape, bool)) is None
