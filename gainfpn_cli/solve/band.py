"""The band of the sensor's gains that the accurate solver never estimates (docs/method.md section 11).

Small motion cannot observe the gains' low spatial frequencies: the solver penalises them
(``mu G`` in ``(I - M + mu G) x = M 1 - 1``, docs/method.md section 8) and the gauge divides k by
its own low-pass ``G``. For a scene point seen by every frame, ``M`` averages the partners'
readings at the frames' displacements ``d_t - d_s``, so at spatial frequency ``f`` the solve keeps

    T(f) = (1 - g(f)) m(f) / (m(f) + mu g(f)),   m(f) = mean over pairs (s, t) of 1 - exp(2 pi i f . (d_t - d_s)),

``g`` the Gaussian low-pass's response, of the gains' true pattern and loses ``1 - T(f)`` of it
(``m`` is real, ``1 - cos``, where every pair is compared both ways).
A white pixel FPN of variance ``s^2`` then leaves ``s^2`` times the mean of ``(1 - T)^2`` over the
frequencies at every pixel, an error every fit of the burst makes alike. Measured on a noise-free
240x320 8-bit burst (procedural scene, seed 1, 8 frames): the error's share of the true pattern
0.98 / 0.91 / 0.42 / 0.04 at 0.01-0.02 / 0.02-0.03 / 0.03-0.05 / 0.05-0.08 cycles per pixel, this
model 0.98 / 0.87 / 0.40 / 0.03 (the gauge alone 0.75 / 0.45 / 0.13 / 0.01).

Also the error the scene solver's pixels share, which k's own band shows (:func:`shared_band`).
"""

from __future__ import annotations

import numpy as np

#: Frequency grid step (cycles per pixel) :func:`lost_share` averages over: 10 or more samples per
#: period of a pair's ``exp(2 pi i f . d)`` for displacements up to :data:`RESOLVED` px.
STEP = 1.0 / 512
#: Pairs displaced further than this (px) count at their mean over frequency, ``m = 1``: at the
#: frequencies where that is wrong, below ``1 / d``, the gauge takes all of the band anyway.
RESOLVED = 0.1 / STEP


def lost_share(shifts: np.ndarray, pairs, gauge_sigma: float, mu: float) -> float:
    """The share of a white gain pattern's variance the accurate solver loses (see the module):
    ``shifts`` (F, 2) each frame's displacement (x, y) in the plane's pixels, ``pairs`` the (anchor,
    partner) frame indices it compares, ``gauge_sigma`` and ``mu`` its options."""
    shifts = np.asarray(shifts, np.float64)
    reach = min(0.5, 4.0 / (np.pi * gauge_sigma))  # g(f) < 1e-13 beyond
    axis = np.arange(-reach, reach + STEP / 2, STEP)
    fx, fy = np.meshgrid(axis, axis)
    g = np.exp(-2.0 * np.pi**2 * gauge_sigma**2 * (fx**2 + fy**2))
    phase = {t: np.exp(2j * np.pi * (fx * dx + fy * dy)) for t, (dx, dy) in enumerate(shifts)}  # a frame's, once
    m = np.zeros(g.shape, complex)
    for s, t in pairs:
        m += 1.0 if np.hypot(*(shifts[t] - shifts[s])) > RESOLVED else 1.0 - phase[t] * np.conj(phase[s])
    m /= max(len(pairs), 1)
    denominator = m + mu * g
    kept = (1.0 - g) * np.divide(m, denominator, out=np.zeros_like(m), where=np.abs(denominator) > 0)
    return float(np.sum(np.abs(1.0 - kept) ** 2) * STEP**2)


def shifts_at_centre(homographies, S: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Each frame's displacement (x, y) at the centre of a grid of ``shape`` whose pixels ``S`` maps
    to frame pixels, in the grid's pixels; ``homographies`` are ``H_t_ref`` in frame pixels."""
    centre = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
    S_inv = np.linalg.inv(S)
    moved = np.stack([S_inv @ H @ S @ centre for H in homographies])
    return moved[:, :2] / moved[:, 2:] - centre[:2]


def gauge_share(gauge_sigma: float) -> float:
    """The share of a white gain pattern's variance a gauge alone loses: its Gaussian low-pass of
    ``gauge_sigma`` px averages ``4 pi gauge_sigma^2`` pixels (the scene solver, whose latent scene
    observes the low band apart from its gauge)."""
    return 1.0 / (4.0 * np.pi * gauge_sigma**2)


#: Gaussian sigma (px) of the band of k in which :func:`shared_band` measures an error the pixels
#: share, and (times :data:`SHARED_REACH`) of the neighbourhood its power is averaged over. On the
#: scene solver's 240x320 8-bit bursts of ``coffee`` and ``rocket`` (50 %, 9 frames; the tuning
#: bursts) a band of 4 px averaged over 16 px took the lowest tenth of sigma_k from 1.33 / 1.26 to
#: 1.12 / 0.98 (``python docs/bench/confidence.py coffee,rocket paper 9``; a band of 8 px read 1.19 /
#: 1.01, of 16 px 1.24 / 1.02 on the same maps: the error lies at 4-16 px). On white
#: gains the neighbourhoods' scatter, clipped at 0, adds 6-22 % of the white band's power (10 seeds of
#: 240x320 5 % FPN, the map shrunk: 0.008-0.027 %^2 of 0.120 %^2 at 1 % error, 7-20 % at 5 %).
SHARED_SIGMA = 4.0
SHARED_REACH = 4.0


def shared_band(k: np.ndarray, sigma: np.ndarray, est: np.ndarray, fpn: float) -> np.ndarray:
    """Per pixel, the variance of an error the pixels near it share, measured on ``k`` itself: the
    power of k's band wider than :data:`SHARED_SIGMA` px (averaged over :data:`SHARED_REACH` times
    that) beyond what a white pixel FPN and k's own errors put there; 0 where k is not estimated
    (``est`` False) or nothing is left.

    ``k`` is a pixel model's written map (gauged: its low band is 1): each pixel's deviation shrunk
    by ``w = s^2 / (s^2 + sigma_0^2)``, ``s = fpn`` (relative) the prior, ``sigma = sqrt(w) sigma_0``
    its written sigma_k. A white deviation of variance ``s^2 + sigma_0^2`` so holds
    ``w^2 (s^2 + sigma_0^2) = s^2 - sigma^2``, of which a band of ``b`` px keeps ``1 / (4 pi b^2)``;
    a shared error ``e`` it holds as ``w e``, which is what the written sigma_k must count.

    The scene solver's noise probe sees the noise; a misfit the latent scene and the gains trade
    over a few pixels (interpolation of sharp detail, a warp's residual error) moves k alike over
    them, and a gain pattern that has no such band is told from it: its white part is subtracted.
    A real gain pattern with structure at these scales, and a column or row base the pixel model
    keeps in k (which on the scene solver's bursts is mostly error: docs/method.md section 11),
    is read as error."""
    from ..geometry.resample import low_pass

    reach = SHARED_REACH * SHARED_SIGMA
    band = np.where(est, low_pass(k, SHARED_SIGMA, est) - 1.0, 0.0)
    power = low_pass(band**2, reach, est)
    white = np.where(est, np.maximum(fpn**2 - sigma**2, 0.0), 0.0)  # (sigma is inf where not estimated)
    excess = power - low_pass(white, reach, est) / (4.0 * np.pi * SHARED_SIGMA**2)
    return np.where(est, np.maximum(excess, 0.0), 0.0)
