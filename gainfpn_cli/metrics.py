"""Figures of merit against a known truth (simulated bursts).

* residual gain FPN: robust spread of ``k * a`` after normalising its median
  to 1, in percent (1.4826 x median absolute deviation, so it equals the
  standard deviation for Gaussian scatter and ignores a few wild pixels);
* MSE (the paper's): mean of ``(frame - ideal)^2`` over evaluated pixels,
  before correction and after multiplying by ``k``.
"""

from __future__ import annotations

import numpy as np


def robust_spread(values: np.ndarray) -> float:
    """1.4826 * MAD of ``values / median(values)``: a robust relative sigma."""
    values = np.asarray(values, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan")
    rel = values / np.median(values)
    return float(1.4826 * np.median(np.abs(rel - np.median(rel))))


def residual_fpn_percent(k: np.ndarray, gain: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Robust spread of ``k * a`` (what is left of the gain FPN), percent."""
    product = np.asarray(k, np.float64) * np.asarray(gain, np.float64)
    return 100.0 * robust_spread(product if mask is None else product[mask])


def mse(frame: np.ndarray, ideal: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared difference in DN^2, over ``mask`` when given."""
    diff = np.asarray(frame, np.float64) - np.asarray(ideal, np.float64)
    return float(np.mean(diff**2 if mask is None else diff[mask] ** 2))


def interior_mask(shape: tuple[int, int], margin: int) -> np.ndarray:
    """True away from a ``margin``-pixel border (where trajectories leave the frame)."""
    mask = np.zeros(shape, bool)
    mask[margin : shape[0] - margin, margin : shape[1] - margin] = True
    return mask
