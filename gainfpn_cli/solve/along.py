"""Statistics of a plane's readings against a predicted scene, photosite by photosite along the
frames, for the defect search (:mod:`solve.defects`, :mod:`solve.leftout`): the response (the median
ratio of reading to scene), an offset fitted with the gain, and robust spreads of such scores."""

from __future__ import annotations

import numpy as np

from ..metrics import MAD_TO_SIGMA
from .stacks import each_strip, nan_median

#: Fewest frames, predicted from the other frames, that the offset is fitted on. At 5, ten
#: defect-free 144x176 raw12 dead-leaves bursts of 5 frames (seeds 20-29, true motion) had 9 more
#: healthy photosites flagged (56 against 47 of 253 440), the table's 240x320 ones 0-1 more.
MIN_FIT_FRAMES = 6
#: Scale of the Cauchy weights of the offset fit, in standard deviations of a reading: the
#: frames where the prediction misses (an edge, a border) stop pulling the fit (95 % efficiency
#: at Gaussian errors). The weights are those of the robust start (the plane's gain, the median
#: offset): reweighting twice more changed the table's detections by at most 0.6 % of the hot
#: photosites.
CAUCHY_SCALE = 2.385
#: E[c^2 u^2 / (1 + u^2)] for a unit Gaussian residual (u = r / c, c = CAUCHY_SCALE): the fit's own
#: Cauchy-weighted scatter is divided by it, so that Gaussian residuals of the model's variance
#: give 1 (Monte Carlo, 10^7 draws).
CAUCHY_CONSISTENCY = 0.697


def responses(y: np.ndarray, x: np.ndarray, usable: np.ndarray, threads: int = 1) -> tuple[np.ndarray, ...]:
    """Per photosite: the median over frames of ``y / x``, its robust scatter, the count, the
    lowest, the highest, and the mean ``x`` (a strip at a time on ``threads`` threads:
    :func:`stacks.each_strip`)."""
    out = [np.zeros(y.shape[1:], np.float32) for _ in range(5)]

    def work(rows):
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(usable[:, rows], y[:, rows] / x[:, rows], np.float32(np.nan))
        response = nan_median(ratio)
        scatter = MAD_TO_SIGMA * nan_median(np.abs(ratio - response[None]))
        # np.nanmin's, np.nanmax's and np.nanmean's results (NaN where no frame is usable), without
        # their warnings, whose filters are not the thread's own as NumPy's error state is
        level = np.where(usable[:, rows], x[:, rows], np.float32(0)).sum(axis=0)
        with np.errstate(invalid="ignore"):
            np.true_divide(level, usable[:, rows].sum(axis=0, dtype=np.intp), out=level, casting="unsafe")
        parts = (response, scatter, np.fmin.reduce(ratio, axis=0), np.fmax.reduce(ratio, axis=0), level)
        for whole, part in zip(out, parts):
            whole[rows] = np.nan_to_num(part)

    each_strip(work, y.shape, threads=threads)
    response, scatter, lowest, highest, level = out
    return response, scatter, usable.sum(axis=0), lowest, highest, level


def offset_scores(y: np.ndarray, x: np.ndarray, fitted: np.ndarray, typical: float, spread: float,
                   scatter: np.ndarray, noise, threads: int = 1) -> np.ndarray:
    """Per photosite, the offset ``b`` of ``y_t = a x_t + b`` fitted to its readings in the frames
    ``fitted``, over its standard error, in units of the plane's (and where larger its 5x5
    neighbourhood's) robust spread of that score; 0 where fewer than :data:`MIN_FIT_FRAMES` are
    fitted. The gain ``a`` has the plane's as prior (``typical``, ``spread``): along a flat
    trajectory the offset is then the response's excess, across an edge the two are told apart.
    A reading's variance is the noise at the photosite's mean level or, where larger, the
    prediction's error around it (the 5x5 median of the ratios' ``scatter`` over the frames times
    the level); the frames are Cauchy-weighted by their residuals about a robust start (the
    plane's gain, the median offset), and the error is scaled up by the fit's own scatter where
    that is larger. A quarter strip at a time on ``threads`` threads (:func:`stacks.each_strip`)."""
    count = fitted.sum(axis=0)
    level = np.zeros(count.shape, np.float32)

    def mean_level(rows):
        level[rows] = np.where(fitted[:, rows], x[:, rows], 0).sum(axis=0) / np.maximum(count[rows], 1)

    each_strip(mean_level, y.shape, threads=threads)
    var = np.maximum(noise(level), local_median(scatter * level) ** 2).astype(np.float32)
    root_weight = 1.0 / np.sqrt(np.maximum(var, 1e-12))  # noise-free data: no zero division
    prior = 1.0 / max(spread, 1e-6) ** 2
    score = np.zeros(count.shape)
    tested = count >= MIN_FIT_FRAMES

    def fit(rows):  # a dozen temporaries of a quarter strip's stack
        # (fewer frames: no fit, whose 2x2 system from one frame would be cancellation's noise)
        use = fitted[:, rows] & tested[rows]
        ys, xs = np.where(use, y[:, rows], np.float32(0)), np.where(use, x[:, rows], np.float32(0))
        root = use * (root_weight[rows] / CAUCHY_SCALE)  # z / c of a residual: residual x root
        start = ys - typical * xs
        start -= np.nan_to_num(nan_median(np.where(use, start, np.nan)))
        w = root * root / (1 + (start * root) ** 2) * CAUCHY_SCALE**2
        # about the weighted means: the sums' differences cancel to noise where the weights are
        # large (noise-free readings) and x barely moves along the trajectory
        s1 = np.maximum(w.sum(0, np.float64), 1e-300)
        mx, my = (w * xs).sum(0, np.float64) / s1, (w * ys).sum(0, np.float64) / s1
        dx = xs - mx.astype(np.float32)
        sxx = (w * dx * dx).sum(0, np.float64) + prior  # the gain's information, its prior's included
        a = ((w * dx * ys).sum(0, np.float64) + prior * typical) / sxx
        b = (my - a * mx).astype(np.float32)
        u = (ys - a.astype(np.float32) * xs - b) * root
        own = CAUCHY_SCALE**2 * (u * u / (1 + u * u)).sum(0, np.float64) / np.maximum(count[rows] - 2, 1)
        variance = 1.0 / s1 + mx * mx / sxx  # b's, in units of the readings' weights
        score[rows] = b / np.sqrt(variance * np.maximum(own / CAUCHY_CONSISTENCY, 1.0))

    each_strip(fit, y.shape, parts=4, threads=threads)
    if not tested.any():
        return np.zeros(count.shape)
    centre, _, scale = robust_spread(score, tested)
    score -= centre
    score /= np.maximum(scale, 1e-12, out=scale)
    score[~tested] = 0.0
    return score


def centre_and_spread(picked: np.ndarray) -> tuple[float, float]:
    """The median of the values ``picked`` (a copy, overwritten: no other temporary) and their robust
    spread, MAD_TO_SIGMA times their median absolute deviation from it."""
    centre = float(np.median(picked, overwrite_input=True))
    np.abs(np.subtract(picked, centre, out=picked), out=picked)
    return centre, MAD_TO_SIGMA * float(np.median(picked, overwrite_input=True))


def robust_spread(values: np.ndarray, tested: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The median of ``values`` over the ``tested`` photosites, their robust spread (MAD), and
    per photosite that spread or, where larger, the robust spread of the tested values about the
    median over its 5x5 neighbourhood."""
    # (in place: each temporary is a plane's, 96 MB at 12 MP in float64)
    centre, spread = centre_and_spread(values[tested])
    deviation = np.abs(np.subtract(values, centre, dtype=values.dtype), dtype=values.dtype)
    deviation[~tested] = 0.0
    around = local_median(deviation)
    del deviation
    around *= MAD_TO_SIGMA
    return centre, spread, np.maximum(spread, around, out=around)


def local_median(values: np.ndarray) -> np.ndarray:
    """Median over each pixel's 5x5 neighbourhood (OpenCV's median filter takes float32 at 5)."""
    import cv2

    return cv2.medianBlur(np.ascontiguousarray(values, np.float32), 5).astype(np.float64)
