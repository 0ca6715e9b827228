"""Figures of merit against a known truth (simulated bursts).

* residual gain FPN: robust spread of ``k * a`` after normalising its median
  to 1, in percent (1.4826 x median absolute deviation, so it equals the
  standard deviation for Gaussian scatter and ignores a few wild pixels);
* MSE (the paper's): mean of ``(frame - ideal)^2`` over evaluated pixels,
  before correction and after multiplying by ``k``.
"""

from __future__ import annotations

import numpy as np

#: Standard deviation of a normal distribution per unit of its median absolute deviation
#: (1 / Phi^-1(3/4)): ``MAD_TO_SIGMA * MAD`` is the robust spread used throughout.
MAD_TO_SIGMA = 1.4826


def robust_spread(values: np.ndarray) -> float:
    """1.4826 * MAD of ``values / median(values)``: a robust relative sigma."""
    values = np.asarray(values, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan")
    rel = values / np.median(values)
    return float(MAD_TO_SIGMA * np.median(np.abs(rel - np.median(rel))))


def chi2_quantile(q: float, dof: float) -> float:
    """Chi-square's ``q`` quantile with ``dof`` degrees of freedom, ``2 gammaincinv(dof / 2, q)``
    (scipy.stats' ``chi2.ppf`` without its import)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(dof / 2.0, q))


def residual_fpn_percent(k: np.ndarray, gain: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Robust spread of ``k * a`` (what is left of the gain FPN), percent."""
    product = np.asarray(k, np.float64) * np.asarray(gain, np.float64)
    return 100.0 * robust_spread(product if mask is None else product[mask])


def mse(frame: np.ndarray, ideal: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared difference in DN^2, over ``mask`` when given."""
    diff = np.asarray(frame, np.float64) - np.asarray(ideal, np.float64)
    return float(np.mean(diff**2 if mask is None else diff[mask] ** 2))


def confidence_deciles(k: np.ndarray, gain: np.ndarray, sigma: np.ndarray, mask: np.ndarray,
                       parts: int = 10) -> list[float]:
    """Is ``sigma`` (the written sigma_k) the error ``k`` has? Per ``parts``-quantile of ``sigma`` over
    ``mask``, the RMS of the actual relative error of ``k`` (``k * a`` over its mean, minus 1) over the
    RMS of ``sigma``: 1 is honest, above 1 the confidence is too high. Empty where ``mask`` holds fewer
    pixels than ``parts``."""
    product = (np.asarray(k, np.float64) * np.asarray(gain, np.float64))[mask]
    predicted = np.asarray(sigma, np.float64)[mask]
    if product.size < parts:
        return []
    error = product / product.mean() - 1.0
    return [float(np.sqrt(np.mean(error[part] ** 2) / np.mean(predicted[part] ** 2)))
            for part in np.array_split(np.argsort(predicted, kind="stable"), parts)]


def interior_mask(shape: tuple[int, int], margin: int) -> np.ndarray:
    """True away from a ``margin``-pixel border (where trajectories leave the frame)."""
    mask = np.zeros(shape, bool)
    mask[margin : shape[0] - margin, margin : shape[1] - margin] = True
    return mask


def gain_bound(electrons: np.ndarray, *, n_frames: int, read_noise_e: float, dn_per_e: float,
               shot_noise: bool = True, prior: float | None = None) -> np.ndarray:
    """Per-pixel lower bound on the relative standard error of an estimated gain.

    The Cramer-Rao bound of a pixel's gain from its own ``n_frames`` readings
    of ``electrons`` each (every frame assumed as bright there as the one
    given), with the scene known exactly: each reading's Fisher information
    on the relative gain is ``e^2 / (e + r^2 + q^2 / 12)`` (shot noise, read
    noise ``r`` and the ADC's step ``q = 1 / dn_per_e`` electrons). With
    ``prior``, the spread of the pixel gains (the information a shrinkage
    estimator adds), the Bayesian bound ``1 / sqrt(I + 1 / prior^2)``.
    No estimator that learns a pixel's gain from its readings does better on
    average; one that must also estimate the scene does worse.
    """
    e = np.clip(np.asarray(electrons, np.float64), 0.0, None)
    variance = (e if shot_noise else 0.0) + read_noise_e**2 + 1.0 / (12.0 * dn_per_e**2)
    with np.errstate(divide="ignore"):
        information = n_frames * e**2 / variance + (0.0 if prior is None else np.float64(1.0) / np.square(prior))
        return 1.0 / np.sqrt(information)


def mixture_spread(sigmas: np.ndarray) -> float:
    """:func:`robust_spread` (x 1, not percent) that zero-mean Gaussian errors of these
    per-pixel standard deviations show in expectation: ``1.4826 m`` with
    ``mean(P(|N(0, s_i^2)| < m)) = 1/2``."""
    from scipy.optimize import brentq
    from scipy.special import erf

    s = np.asarray(sigmas, np.float64).ravel()
    s = s[np.isfinite(s)]
    if s.size == 0:
        return float("nan")
    below = lambda m: float(np.mean(erf(m / (np.sqrt(2.0) * s)))) - 0.5  # noqa: E731
    return MAD_TO_SIGMA * brentq(below, 0.0, 10.0 * float(s.max()))


def point_noise_variance(distances: np.ndarray) -> float:
    """Per-coordinate variance of 2-D Gaussian errors from their lengths: median(d^2) = 2 ln 2 sigma^2."""
    return float(np.median(distances**2)) / (2 * np.log(2))
