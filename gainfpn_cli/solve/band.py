"""The band of the sensor's gains that the accurate solver never estimates (docs/method.md section 11).

Small motion cannot observe the gains' low spatial frequencies: the solver penalises them
(``mu G`` in ``(I - M + mu G) x = M 1 - 1``, docs/method.md section 8) and the gauge divides k by
its own low-pass ``G``. For a scene point seen by every frame, ``M`` averages the partners'
readings at the frames' displacements ``d_t - d_s``, so at spatial frequency ``f`` the solve keeps

    T(f) = (1 - g(f)) m(f) / (m(f) + mu g(f)),   m(f) = mean over pairs (s, t) of 1 - cos(2 pi f . (d_t - d_s)),

``g`` the Gaussian low-pass's response, of the gains' true pattern and loses ``1 - T(f)`` of it.
A white pixel FPN of variance ``s^2`` then leaves ``s^2`` times the mean of ``(1 - T)^2`` over the
frequencies at every pixel, an error every fit of the burst makes alike. Measured on a noise-free
240x320 8-bit burst (procedural scene, seed 1, 8 frames): the error's share of the true pattern
0.98 / 0.91 / 0.42 / 0.04 at 0.01-0.02 / 0.02-0.03 / 0.03-0.05 / 0.05-0.08 cycles per pixel, this
model 0.98 / 0.87 / 0.40 / 0.03 (the gauge alone 0.75 / 0.45 / 0.13 / 0.01).
"""

from __future__ import annotations

import numpy as np

#: Frequency grid step (cycles per pixel) :func:`lost_share` averages over; the loss ends below
#: 0.1 cycles per pixel for a gauge of 8 px (its response exp(-2 pi^2 sigma^2 f^2) is 3e-6 at 0.1).
STEP = 1.0 / 512


def lost_share(shifts: np.ndarray, pairs, gauge_sigma: float, mu: float) -> float:
    """The share of a white gain pattern's variance the accurate solver loses (see the module):
    ``shifts`` (F, 2) each frame's displacement (x, y) in the plane's pixels, ``pairs`` the (anchor,
    partner) frame indices it compares, ``gauge_sigma`` and ``mu`` its options."""
    shifts = np.asarray(shifts, np.float64)
    reach = min(0.5, 4.0 / (np.pi * gauge_sigma))  # g(f) < 1e-13 beyond
    axis = np.arange(-reach, reach + STEP / 2, STEP)
    fx, fy = np.meshgrid(axis, axis)
    g = np.exp(-2.0 * np.pi**2 * gauge_sigma**2 * (fx**2 + fy**2))
    m = np.zeros_like(g)
    for s, t in pairs:
        dx, dy = shifts[t] - shifts[s]
        m += 1.0 - np.cos(2.0 * np.pi * (fx * dx + fy * dy))
    m /= max(len(pairs), 1)
    kept = (1.0 - g) * np.divide(m, m + mu * g, out=np.zeros_like(m), where=m + mu * g > 0)
    return float(np.sum((1.0 - kept) ** 2) * STEP**2)


def gauge_share(gauge_sigma: float) -> float:
    """The share of a white gain pattern's variance a gauge alone loses: its Gaussian low-pass of
    ``gauge_sigma`` px averages ``4 pi gauge_sigma^2`` pixels (the scene solver, whose latent scene
    observes the low band apart from its gauge)."""
    return 1.0 / (4.0 * np.pi * gauge_sigma**2)
