"""sigma_k's calibration on a synthetic burst's error (solve/bootstrap.py): the factor per tenth."""

import numpy as np
import pytest

from gainfpn_cli.solve.bootstrap import calibration, raised
from gainfpn_cli.solve.halves import Calibration


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


def test_the_model_burst_raises_the_halves_factors_and_keeps_their_prior():
    # the halves read 0.8 / 1.0 / 1.3 at sigma 0.2 / 0.4 / 0.8 %; the model's burst 1.1 / 1.2 from 0.3 to 0.6 %:
    # each halves' factor rises to the model's at its own sigma (interpolated in log sigma, the end
    # ones beyond), never falls
    halves = Calibration(np.log([0.002, 0.004, 0.008]), np.array([0.8, 1.0, 1.3]), 2.5e-3, prior_se=1e-4)
    floor = Calibration(np.log([0.003, 0.006]), np.array([1.1, 1.2]), None)
    got = raised(halves, floor)
    np.testing.assert_allclose(got.factor, [1.1, 1.1 + 0.1 * np.log(4 / 3) / np.log(2), 1.3])
    assert (got.prior, got.prior_se, got.measured) == (2.5e-3, 1e-4, True)
    assert raised(halves, None) is halves
    assert raised(None, floor) is floor  # halves that measured too few pixels
    assert raised(Calibration(np.zeros(1), np.ones(1), 2e-3, measured=False), floor) is floor
