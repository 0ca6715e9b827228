"""Phase weights (``solver.phase_weights``): each comparison weighted by how well interpolation
predicts it where its sample falls between pixels (docs/method.md section 10)."""

from __future__ import annotations

import numpy as np

from ..geometry.resample import positions, window_sum

#: Side (px) of the window over which the interpolation error's growth with the phase is fitted.
PHASE_WINDOW = 9


def sample_phase(M: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``sin^2(pi fx) + sin^2(pi fy)`` of where each sample of ``M`` falls (``f``: the position's
    fractional part): 0 on a source pixel, where interpolation is exact; 2 midway between four."""
    pos = positions(M, shape).astype(np.float32)
    return np.sin(np.float32(np.pi) * pos[..., 0]) ** 2 + np.sin(np.float32(np.pi) * pos[..., 1]) ** 2


def phase_weighted(weights, residuals, valid, pair_maps, shape) -> list[np.ndarray]:
    """``weights`` times each comparison's precision ``u / (a + b phase)`` (in place: fresh arrays only).

    Interpolation errs little where a sample falls near a source pixel and
    most midway between pixels, and more where the scene is sharper than the
    grid (an aliased CFA plane). ``a + b phase`` (``a``: noise, ``b`` >= 0:
    interpolation error) is fitted by least squares to the squared residuals
    of all comparisons in a window around each pixel; ``u`` is the median of
    ``a``, so that a comparison as good as the noise keeps its weight.
    """
    box = lambda a: window_sum(a, PHASE_WINDOW)  # noqa: E731
    moments = np.zeros((5,) + shape)  # sums of 1, p, p^2, r^2, r^2 p over valid comparisons
    for r, v, (_, _, M) in zip(residuals, valid, pair_maps):
        p = np.where(v, sample_phase(M, shape), 0.0)
        r2 = np.where(v, r * r, 0.0)
        moments += (v, p, p * p, r2, r2 * p)
    n, sp, spp, sr, srp = (box(m) for m in moments)
    det = n * spp - sp * sp
    fitted = det > 1e-6 * np.maximum(n * spp, 1e-300)  # the window's phases vary
    b = np.maximum(np.divide(n * srp - sp * sr, det, out=np.zeros(shape), where=fitted), 0.0)
    a = np.divide(sr - b * sp, n, out=np.zeros(shape), where=n > 0)
    seen = n > 0
    unit = float(np.median(a[seen])) if seen.any() else 1.0
    a = np.maximum(a, 0.1 * unit if unit > 0 else 1e-300)  # the noise is never fitted below a tenth of the typical
    unit = unit if unit > 0 else 1.0
    for wt, (_, _, M) in zip(weights, pair_maps):  # in place: a tile of 16 frames holds 128 of them
        wt *= unit / (a + b * sample_phase(M, shape))
    return weights
