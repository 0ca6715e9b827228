"""Choose the simplest gain-FPN model the estimate supports.

Candidates, from fewest parameters to most:

* ``none``: k = 1;
* ``row``: even/odd row gains (the paper saw them on silicon);
* ``column``: one gain per column;
* ``column+row``: both;
* ``pixel``: every pixel's own gain on top of the best structured model.

A structured model averages each gain over a whole column or half the rows,
so it is far less noisy than per-pixel k when the sensor's FPN really is
structured. The choice minimises Akaike's criterion

    AIC = sum_q ((k(q) - model(q)) / sigma_k(q))^2 + 2 p,

``sigma_k`` the solver's predicted standard error of each k and ``p`` the
parameters beyond the overall scale (the gauge fixes it for every model):
0, 1, W - 1, W and N - 1 (every pixel's own k, which fits exactly). With
``sigma_k`` calibrated (below), the pixel model is scored as written (shrunk):
its misfit ``sum ((1 - w) d / sigma_k)^2`` and the best structured model's
parameters plus one for the prior's variance and the effective number of its
own, ``sum w`` (the trace of the shrinkage; Hastie & Tibshirani 1990), so a
pixel FPN the noise hides adds next to nothing and loses by the prior's one.
(With the solver's sigma_k, too small on most bursts, the prior takes up the
noise it misses and that score would pick the pixel model on a column-FPN
sensor.) AIC
estimates the prediction error on held-out data (it is asymptotically
leave-one-out cross-validation, Stone 1977), which is what matters when the
map corrects other captures.

Once chosen, the pixel model does not take each pixel's k as it is: a pixel
whose k is uncertain would carry its whole estimation error into the
correction. Its deviation ``d`` from the best structured model is shrunk to
its posterior mean under a normal prior of the sensor's pixel FPN, ``w d``
with ``w = s^2 / (s^2 + sigma_k^2)`` (empirical Bayes; ``s^2`` by the
Paule-Mandel equation ``sum d^2 / (s^2 + sigma_k^2) = N``, each term of which
expects 1). ``s`` comes out as the sensor's pixel FPN plus whatever the
solver's ``sigma_k`` misses. Measured (MSE reduction without -> with the
shrinkage; 320x240x8, motion estimated, all 8 frames fitted): dead leaves
11.7x -> 13.8x; with a 1 px distortion 9.1x -> 13.0x; a raw12 CFA burst of
the procedural scene 0.7x -> 1.3x; a procedural scene 23.2x -> 23.8x.

Given two more fits on disjoint halves of the frames (:class:`Halves`), both
are measured instead (:func:`calibrate`): the halves' errors are nearly
independent, so ``s^2`` is the covariance of their deviations (noise does not
enter it), and the full fit's error variance in each decile of ``sigma_k``
(fewer parts on a plane short of 10 000 pixels: :data:`PART_PIXELS`) is
``-mean((k_a - k)(k_b - k))`` (a Hausman-type difference: exact when k is the
halves' average, and needing no truth); ``sigma_k`` is scaled by the measured
factor. An error the halves share (interpolating a sharp scene) enters neither the Hausman
difference nor the noise, but the covariance; the pixel FPN does not know the scene, so ``s^2``
is pooled from the deciles that agree with the most precise (:func:`_prior`), and what the
deviations' variance holds beyond ``s^2`` and the Hausman difference is counted as error.
Where the full fit strays from the halves' mean by more than their spread allows
(:func:`departure`), that error is added to ``sigma_k`` and those pixels are left out of the
deciles' measurement. The measured calibration is in docs/limits.md ("Confidence").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry.resample import masked_window_mean
from ..metrics import robust_spread
from . import FPN_MODELS
from .result import regauge, sigma_from_confidence

MODELS = FPN_MODELS


@dataclass(frozen=True)
class FPNModel:
    """The chosen model, its gain map and the FPN split.

    Attributes
    ----------
    k : ndarray of float32, shape (H, W)
        The correction under the chosen model.
    chosen : str
    scores : dict
        AIC of every candidate (lower is better).
    split : dict
        Estimated input gain FPN in percent: ``pixel``, ``column``, ``row``
        (spread of the gains ``1 / k`` attributed to each part; the pixel
        part is the prior's ``s``: the spread of k less its estimation noise).
    calibration : Calibration or None
        What two halves of the frames measured (or were given), if anything.
    sigma : ndarray of float32 or None
        With a calibration, the predicted standard error of each written k:
        the calibrated ``sigma_k`` shrunk with k (``sqrt(w) sigma_k``) by the
        pixel model, as it is under a structured one (an upper bound there).
    """

    k: np.ndarray
    chosen: str
    scores: dict = field(default_factory=dict)
    split: dict = field(default_factory=dict)
    calibration: Calibration | None = None
    sigma: np.ndarray | None = None  # with a calibration: the predicted standard error of k


@dataclass(frozen=True)
class Halves:
    """k fitted again on two disjoint halves of the frames (before any FPN model), on part of the
    plane: confidence 0 where a half has no estimate."""

    k_a: np.ndarray
    confidence_a: np.ndarray
    k_b: np.ndarray
    confidence_b: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """What two halves measured (:func:`calibrate`): the factor that scales ``sigma_k`` to k's
    actual error, at the RMS ``sigma_k`` of each decile (between them, interpolated in
    ``log sigma_k``; beyond them, the end ones), and the pixel FPN prior ``s^2`` (None: from the
    deviations). ``measured`` is False for the solver's ``sigma_k`` taken as it is (factor 1)."""

    log_sigma: np.ndarray
    factor: np.ndarray
    prior: float | None
    measured: bool = True

    def sigma(self, sigma: np.ndarray) -> np.ndarray:
        """``sigma_k`` (the solver's) scaled to k's actual error; inf stays inf."""
        sigma = np.asarray(sigma, np.float32)
        finite = np.isfinite(sigma) & (sigma > 0)
        scale = np.interp(np.log(np.where(finite, sigma, 1)), self.log_sigma, self.factor).astype(np.float32)
        return np.where(finite, sigma * scale, sigma)


#: Side (px) of the window whose mean sigma_k^2 orders the deciles the pixel FPN is pooled over
#: (:func:`local_sigma2`, :func:`_prior`).
LOCAL_WINDOW = 5


def local_sigma2(sigma: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The mean ``sigma_k^2`` over the :data:`LOCAL_WINDOW` window's ``mask`` pixels (0 where there are
    none). A pixel's own sigma_k falls with its own gain (its readings' information), so its
    deciles would slice the pixel FPN itself where the scene is flat; the window's mean follows the scene.
    (k's error does follow a pixel's own sigma_k: the calibration's deciles are by that.)"""
    return masked_window_mean(np.asarray(sigma, np.float32) ** 2, mask, LOCAL_WINDOW)


#: Pixels in each part (a tenth of sigma_k, or fewer parts of a plane with fewer pixels) that
#: :func:`calibrate` measures a factor on: 1000 give it to about 5 %.
PART_PIXELS = 1000
#: Most parts :func:`calibrate` cuts the pixels into: tenths of sigma_k.
MAX_PARTS = 10
#: Fewest parts :func:`calibrate` measures: with fewer, one part whose halves' covariance reads low takes
#: the pooled pixel FPN to 0 and the map to k = 1. Measured (mono 12-bit dark dead leaves, 6 fitted frames,
#: 16 seeds, MSE ratio on an unseen frame before the check, geometric mean; the solver's sigma_k -> halves):
#: 64x80 (4 parts) 1.645 -> 1.515, 3 maps lost; 80x96 (6 parts) 1.618 -> 1.581, one lost, one mended. On
#: 160x192 RGGB bursts (planes of 80x96, 6 parts) k errs 1.00-1.09x the written sigma_k, plane by plane.
MIN_PARTS = 6
#: Smallest factor :func:`calibrate` gives ``sigma_k``: a decile whose measured error variance is
#: 0 or below (a chance of its own noise) must not make k certain.
MIN_FACTOR = 0.1


#: A decile's error beyond the halves' Hausman difference (one they share) is taken in with the weight
#: ``t^2 / (SHARED_T2 + t^2)``, ``t`` the excess over its standard error: half of it at 2 standard errors.
#: Measured on synthetic halves (30 seeds, decile factors against the truth): with no shared error, 4 %
#: RMS (a hard cut at 3 standard errors: 1 %, full weight: 6.5 %); on a 9-frame camera RGGB burst, whose
#: shared error stands 2-5 standard errors out, the four planes' residual 1.09 % (a hard cut: 1.17 %,
#: without this term 1.19 %; true FPN 1.0 %; measured with the FPN pooled over deciles of the pixel's own
#: sigma_k, which gave the chosen weight's 1.09 % as the window's does).
SHARED_T2 = 4.0
#: A decile's covariance of the halves' deviations above the pooled pixel FPN variance by more than
#: this many standard errors holds an error the halves share, and is left out of the FPN (:func:`_prior`).
PRIOR_Z = 2.0


#: Side (px) of the window :func:`departure` compares the full fit with the halves' mean over.
DEPARTURE_WINDOW = 5
#: How far (in variance) the full fit must stray from the halves' mean, over the spread the halves
#: give that mean, before :func:`departure` counts it: under a consistent fit the ratio's expectation
#: is at most 1, and a 5x5 window of errors correlated over a few pixels has few degrees of freedom.
DEPARTURE_RATIO = 4.0


def departure(k: np.ndarray, halves: Halves, est: np.ndarray) -> np.ndarray:
    """The variance of an error the full fit ``k`` has and neither half does: the local mean square
    of ``k - (k_a + k_b) / 2`` beyond the halves' own spread ``((k_a - k_b) / 2)^2`` where it is more
    than :data:`DEPARTURE_RATIO` times that spread, else 0 (and 0 where a half has no estimate).

    The full fit is the halves' average plus what their cross comparisons add, so it strays from
    that average by no more than the average's own error; a mode it pins down worse than either
    half (a frame edge that trajectories leave, comparisons of near frames only) strays further,
    and the halves' Hausman difference (:func:`calibrate`) reads that as a smaller error, not a
    larger one."""
    both = est & (halves.confidence_a > 0) & (halves.confidence_b > 0)
    k_a, k_b = (np.asarray(m, np.float32) for m in (halves.k_a, halves.k_b))  # plane-sized: float32
    stray = masked_window_mean((np.asarray(k, np.float32) - (k_a + k_b) / 2) ** 2, both, DEPARTURE_WINDOW)
    spread = masked_window_mean(((k_a - k_b) / 2) ** 2, both, DEPARTURE_WINDOW)
    return np.where(both & (stray > DEPARTURE_RATIO * spread), stray - spread, np.float32(0))


def calibrate(k: np.ndarray, sigma: np.ndarray, halves: Halves, base: np.ndarray,
              est: np.ndarray) -> Calibration | None:
    """The :class:`Calibration` that ``halves`` measure of the full fit ``k`` (``sigma`` its
    solver's ``sigma_k``), with ``base`` the structured model the pixel FPN deviates from; None
    where all three fits see too few pixels for :data:`MIN_PARTS` parts of :data:`PART_PIXELS`."""
    both = est & (halves.confidence_a > 0) & (halves.confidence_b > 0) & np.isfinite(sigma)
    count = min(int(both.sum()) // PART_PIXELS, MAX_PARTS)
    if count < MIN_PARTS:
        return None
    s = sigma[both].astype(np.float64)
    k_full, k_a, k_b = (np.asarray(m, np.float64)[both] for m in (k, halves.k_a, halves.k_b))
    d_full, d_a, d_b = k_full - base[both], k_a - base[both], k_b - base[both]
    parts = np.array_split(np.argsort(s), count)
    prior, prior_se = _prior(d_a, d_b, np.array_split(np.argsort(local_sigma2(sigma, both)[both]), count))
    log_sigma, factor = [], []
    for part in parts:
        square = float(np.mean(s[part] ** 2))
        cross = (k_a[part] - k_full[part]) * (k_b[part] - k_full[part])
        error = -float(np.mean(cross))  # the Hausman difference: what the halves do not share
        # all of k's error: its deviations' variance less the pixel FPN's (FPN does not know the scene;
        # about the decile's mean, which a decile of a flat scene's sigma_k shifts with the gains)
        beyond = (d_full[part] - d_full[part].mean()) ** 2 + cross
        shared = max(float(np.mean(beyond)) - prior, 0.0)
        t2 = shared**2 / max(float(np.var(beyond)) / len(part) + prior_se**2, np.finfo(float).tiny)
        error += shared * t2 / (SHARED_T2 + t2)  # taken in as far as it stands out of its own noise
        log_sigma.append(0.5 * np.log(square))
        factor.append(max(np.sqrt(max(error, 0.0) / square), MIN_FACTOR))
    return Calibration(np.array(log_sigma), np.array(factor), prior)


def _prior(d_a: np.ndarray, d_b: np.ndarray, parts) -> tuple[float, float]:
    """The pixel FPN's variance and its standard error: the covariance of the halves' deviations,
    pooled over the parts (deciles of sigma_k) that agree with it.

    An error both halves share (interpolating a sharp scene) enters their covariance too, most where
    sigma_k is large; the pixel FPN does not know the scene and is the same in every part. The parts
    are taken from the most precise on, each one whose covariance is not above the pooled one by more
    than :data:`PRIOR_Z` standard errors, and pooled with the inverse of their sampling variances."""
    covs, variances = [], []
    for part in parts:
        a, b = d_a[part] - d_a[part].mean(), d_b[part] - d_b[part].mean()
        cov = float(np.mean(a * b))
        covs.append(cov)
        variances.append(max(float(np.mean(a * a) * np.mean(b * b)) + cov**2, np.finfo(float).tiny) / len(part))
    pooled, weight = 0.0, 0.0
    for j in np.argsort(variances):
        if weight > 0 and covs[j] - pooled > PRIOR_Z * np.sqrt(variances[j] + 1.0 / weight):
            continue
        pooled = (pooled * weight + covs[j] / variances[j]) / (weight + 1.0 / variances[j])
        weight += 1.0 / variances[j]
    return max(pooled, 0.0), float(1.0 / np.sqrt(weight))


@dataclass(frozen=True)
class _Sums:
    """Weighted sums over each column's even and odd rows, ``(2, W)`` float64 each: ``w``,
    ``w (k - 1)`` and ``w (k - 1)^2``. Every structured model is a gain per (row parity, column),
    so its fit and its chi-square follow from these alone (one pass over the map, not one per model)."""

    w: np.ndarray
    wd: np.ndarray
    wdd: np.ndarray

    @classmethod
    def of(cls, k: np.ndarray, weight: np.ndarray) -> "_Sums":
        d = k - np.float32(1)  # about k's deviations: no cancellation in the chi-squares
        wd = weight * d
        sums = [np.stack([a[p::2].sum(axis=0, dtype=np.float64) for p in (0, 1)]) for a in (weight, wd, wd * d)]
        return cls(*sums)

    @property
    def wk(self) -> np.ndarray:
        """``w k`` summed per (row parity, column)."""
        return self.wd + self.w

    def chi2(self, fit: np.ndarray) -> float:
        """``sum w (k - fit)^2`` for a model given per (row parity, column), ``(2, W)`` or broadcastable."""
        f = np.broadcast_to(np.asarray(fit, np.float64) - 1.0, self.w.shape)
        return float(np.sum(self.wdd - 2.0 * f * self.wd + f * f * self.w))


def structured_parts(k: np.ndarray, weight: np.ndarray, *, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Column gains ``c`` (W,) and even/odd row gains ``r`` (2,) with ``k ~ c[x] r[y % 2]``.

    Weighted least squares (weights ``weight``, zero for unestimated pixels),
    alternated ``rounds`` times; both normalised to mean 1 where weighted.
    """
    return _structured(_Sums.of(np.asarray(k), np.asarray(weight)), rounds)


def _structured(sums: _Sums, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Alternating weighted least squares of ``k ~ c[x] r[p]``, each normalised to weighted mean 1."""
    wk = sums.wk
    per_column, per_parity = sums.w.sum(axis=0), sums.w.sum(axis=1)
    col, row = np.ones(sums.w.shape[1]), np.ones(2)
    for _ in range(rounds):
        den = (row[:, None] ** 2 * sums.w).sum(axis=0)
        col = np.divide((row[:, None] * wk).sum(axis=0), den, out=np.ones_like(col), where=den > 0)
        col /= np.average(col, weights=np.maximum(per_column, 1e-300)) if per_column.sum() > 0 else 1.0
        den = (col[None, :] ** 2 * sums.w).sum(axis=1)
        row = np.divide((col[None, :] * wk).sum(axis=1), den, out=np.ones(2), where=den > 0)
        row /= np.average(row, weights=per_parity) if per_parity.sum() > 0 else 1.0
    return col, row


def _level(shape: np.ndarray, sums: _Sums) -> np.ndarray:
    """``shape`` (per parity and column) times the scale that fits k best: the other models' fits
    are weighted means, at k's own level, and AIC must compare them on equal terms."""
    den = float(np.sum(shape**2 * sums.w))
    return shape * (float(np.sum(shape * sums.wk)) / den if den > 0 else 1.0)


def select_model(k: np.ndarray, confidence: np.ndarray, *, force: str | None = None,
                 halves: Halves | None = None, calibration: Calibration | None = None,
                 sigma_calibrated: bool = False) -> FPNModel:
    """Pick the model by AIC (or ``force`` one) and report the FPN split.

    Parameters
    ----------
    k, confidence : ndarray, shape (H, W)
        The solver's per-pixel estimate and its confidence
        (:func:`solve.result.sigma_from_confidence` gives ``sigma_k`` back).
    force : str, optional
        One of :data:`MODELS` instead of the AIC choice.
    halves : Halves, optional
        Fits on two halves of the frames: ``sigma_k`` and the prior are measured with them
        (:func:`calibrate`).
    calibration : Calibration, optional
        One measured before (for another fit of the same plane), used as it is.
    sigma_calibrated : bool
        The solver's ``sigma_k`` predicts k's actual error (the scene solver's noise probe, the
        accurate solver's residuals with the share the fit took restored): without halves or a
        calibration it is taken as it is (factor 1, ``Calibration.measured`` False), with the prior
        measured from the deviations.
    """
    if force is not None and force not in MODELS:
        raise ValueError(f"force must be one of {', '.join(MODELS)}, got {force!r}")
    # float32 maps (frame-sized: 48 MB each at 12 MP), float64 sums
    k = np.asarray(k, np.float32)
    confidence = np.asarray(confidence, np.float32)
    est = confidence > 0
    sigma = np.maximum(sigma_from_confidence(confidence), 1e-6).astype(np.float32)
    fit = _Fits.of(k, sigma, est)
    strayed = None if halves is None else departure(k, halves, est)
    if halves is not None and calibration is None:  # measured about the solver's own sigma_k's base
        calibration = calibrate(k, sigma, halves, fit.base, est & (strayed == 0))
    if calibration is not None:
        sigma = calibration.sigma(sigma)
        if strayed is not None:
            sigma = np.sqrt(sigma**2 + strayed)
        fit = _Fits.of(k, sigma, est)
    deviation = np.where(est, k - fit.base, np.float32(0))
    if calibration is None and sigma_calibrated:
        calibration = Calibration(np.zeros(1), np.ones(1), pixel_prior_variance(deviation[est], sigma[est]),
                                  measured=False)
    prior = calibration.prior if calibration is not None and calibration.prior is not None else \
        pixel_prior_variance(deviation[est], sigma[est])
    shrink = np.where(est, np.float32(prior) / (np.float32(prior) + sigma**2), np.float32(0))
    scores = {**fit.scores, "pixel": 2.0 * max(int(est.sum()) - 1, 0)}  # every pixel's own k fits exactly
    if calibration is not None:
        # the pixel model as written (shrunk): its misfit, and the base's parameters, the prior's variance
        # and the effective number of its own (the trace of the shrinkage, sum w: Hastie & Tibshirani 1990)
        misfit = float(np.sum(np.where(est, ((1 - shrink) * deviation / sigma) ** 2, 0), dtype=np.float64))
        scores["pixel"] = misfit + 2.0 * (fit.fits[fit.best][1] + 1.0 + float(np.sum(shrink, dtype=np.float64)))
    chosen = force or min(MODELS, key=lambda m: scores[m])
    written_sigma = None
    if chosen == "pixel":
        model_k = np.where(est, fit.base + shrink * deviation, np.float32(1))
        if calibration is not None:
            written_sigma = np.where(est, np.sqrt(shrink) * np.where(est, sigma, 0), np.float32(np.inf))
    else:  # a structured model knows every pixel of a column / row parity it has seen
        model_k = fit.full(chosen)
        written_sigma = None if calibration is None else sigma
    del shrink
    del deviation
    if est.any():
        regauge(model_k, est)
    if chosen == "pixel":
        model_k[~est] = 1.0
    split = {
        "pixel": 100.0 * float(np.sqrt(prior)),
        "column": 100.0 * robust_spread(1.0 / fit.col[fit.sums.w.sum(axis=0) > 0]) if est.any() else 0.0,
        "row": 100.0 * abs(fit.row[0] - fit.row[1]) / 2.0,
    }
    return FPNModel(model_k.astype(np.float32), chosen, scores, split, calibration, written_sigma)


@dataclass(frozen=True)
class _Fits:
    """The structured models fitted to k with weights ``1 / sigma^2``: each a gain per (row parity,
    column) with its parameters beyond the overall scale (which the gauge fixes), their AIC, the
    column and row parts of ``column+row``, and the best one's map (``base``)."""

    sums: _Sums
    fits: dict
    scores: dict
    col: np.ndarray
    row: np.ndarray
    best: str
    base: np.ndarray

    @classmethod
    def of(cls, k: np.ndarray, sigma: np.ndarray, est: np.ndarray) -> "_Fits":
        weight = np.where(est, np.float32(1) / sigma**2, np.float32(0))
        sums = _Sums.of(k, weight)
        del weight
        col, row = _structured(sums)
        w = k.shape[1]
        wk = sums.wk
        ratio = lambda num, den: np.divide(num, den, out=np.ones_like(num), where=den > 0)  # noqa: E731 (1 where unseen)
        fits = {
            "none": (np.full((1, 1), ratio(wk.sum(keepdims=True), sums.w.sum(keepdims=True))[0, 0]), 0.0),
            "row": (ratio(wk.sum(axis=1), sums.w.sum(axis=1))[:, None], 1.0),
            "column": (ratio(wk.sum(axis=0), sums.w.sum(axis=0))[None, :], w - 1.0),
            "column+row": (_level(row[:, None] * col[None, :], sums), float(w)),
        }
        scores = {name: sums.chi2(fit) + 2.0 * params for name, (fit, params) in fits.items()}
        parity = np.arange(k.shape[0]) % 2
        best = min(fits, key=lambda m: scores[m])
        base = np.broadcast_to(fits[best][0].astype(np.float32), (2, w))[parity]
        return cls(sums, fits, scores, col, row, best, base)

    def full(self, model: str) -> np.ndarray:
        """The structured ``model``'s map, frame-sized."""
        parity = np.arange(self.base.shape[0]) % 2
        return np.broadcast_to(self.fits[model][0].astype(np.float32), (2, self.base.shape[1]))[parity]


#: :func:`pixel_prior_variance` estimates one number: from this many pixels
#: at most (its relative standard error is about ``sqrt(2 / n)``, 0.14 %).
PRIOR_SAMPLES = 2**20


def pixel_prior_variance(deviation: np.ndarray, sigma: np.ndarray) -> float:
    """``s^2`` with ``sum d^2 / (s^2 + sigma^2) = N`` (Paule & Mandel 1982), 0 if the
    deviations ``d`` are no larger than their standard errors ``sigma`` say."""
    from scipy.optimize import brentq

    step = max(1, -(-np.size(deviation) // PRIOR_SAMPLES))  # every step-th pixel: the same s^2 to ~0.2 %
    d2 = np.asarray(deviation, np.float32).ravel()[::step] ** 2
    v = np.asarray(sigma, np.float32).ravel()[::step] ** 2
    excess = lambda s2: float(np.sum(d2 / (np.float32(s2) + v), dtype=np.float64)) - d2.size  # noqa: E731 (decreasing)
    if d2.size == 0 or excess(0.0) <= 0:
        return 0.0
    return float(brentq(excess, 0.0, float(d2.mean(dtype=np.float64)), xtol=1e-12))
