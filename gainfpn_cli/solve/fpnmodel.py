"""Choose the simplest gain-FPN model the estimate supports.

Candidates, from fewest parameters to most:

* ``none``: k = 1;
* ``row``: even/odd row gains (the paper saw them on silicon);
* ``column``: one gain per column;
* ``column+row``: both;
* ``pixel``: every pixel's own gain on top of the best structured model.

The choice minimises Akaike's criterion

    AIC = sum_q ((k(q) - model(q)) / sigma_k(q))^2 + 2 p,

``sigma_k`` the solver's predicted standard error of each k and ``p`` the parameters beyond the overall
scale (the gauge fixes it for every model): 0, 1, W - 1, W and N - 1 (every pixel's own k, which fits
exactly). With ``sigma_k`` calibrated (below), the pixel model is scored as written (shrunk): its misfit
``sum ((1 - w) d / sigma_k)^2`` and the best structured model's parameters plus one for the prior's
variance and the effective number of its own, ``sum w`` (the trace of the shrinkage; Hastie & Tibshirani
1990), so a pixel FPN the noise hides adds next to nothing and loses by the prior's one. (With the
solver's sigma_k, too small on most bursts, the prior takes up the noise it misses and that score would
pick the pixel model on a column-FPN sensor.) AIC estimates the prediction error on held-out data
(asymptotically leave-one-out cross-validation, Stone 1977). It counts the pixels as independent, so an
error that runs along part of a column (interpolating a vertical edge) fits a column model as well as
column FPN does; where k's error is measured (halves, below) a column model is a candidate only if
column gains fitted on the top and bottom halves of the plane apart agree (:func:`column_agreement`), as
a sensor's column FPN does and an edge's does not.

Once chosen, the pixel model shrinks each pixel's deviation ``d`` from the best structured model to its
posterior mean under a normal prior of the sensor's pixel FPN, ``w d`` with ``w = s^2 / (s^2 + sigma_k^2)``
(empirical Bayes; ``s^2`` by the Paule-Mandel equation ``sum d^2 / (s^2 + sigma_k^2) = N``), so that a
pixel whose k is uncertain does not carry its estimation error into the correction (docs/method.md
section 11). The written ``sigma_k`` is the written k's: the posterior's for the pixel model, the pixel
FPN a structured model leaves (``s``) with the error of its own gains (:func:`base_variance`).

Given two more fits on disjoint halves of the frames (:class:`Halves`), both are measured instead
(:func:`calibrate`): the halves' errors are nearly independent, so ``s^2`` is the covariance of their
deviations (noise does not enter it), and the full fit's error variance in each decile of ``sigma_k``
(fewer parts on a plane short of 10 000 pixels: :data:`PART_PIXELS`) is ``-mean((k_a - k)(k_b - k))`` (a
Hausman-type difference: exact when k is the halves' average, and needing no truth); ``sigma_k`` is
scaled by the measured factor. An error the halves share (interpolating a sharp scene) enters neither
the Hausman difference nor the noise, but the covariance; the pixel FPN does not know the scene, so
``s^2`` is pooled from the deciles that agree with the most precise (:func:`_prior`), and what the
deviations' variance holds beyond ``s^2`` and the Hausman difference is counted as error. Where the full
fit strays from the halves' mean by more than their spread allows (:func:`departure`), that error is
added to ``sigma_k`` and those pixels are left out of the deciles' measurement. The measured calibration
is in docs/limits.md ("Confidence").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..metrics import chi2_quantile, robust_spread
from . import FPN_MODELS
from .halves import MIN_PARTS, PART_PIXELS, Calibration, Halves, calibrate, covariance, departure
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
        Estimated input gain FPN in percent: ``pixel``, ``column``, ``row`` (spread of the gains
        ``1 / k`` attributed to each part; the pixel part is the prior's ``s``).
    calibration : Calibration or None
        What two halves of the frames measured (or were given), if anything.
    sigma : ndarray of float32 or None
        With a calibration, the predicted standard error of each written k (see the module).
    column_agreement : float
        Column gains fitted on the plane's top and bottom halves apart agree by this many standard
        errors (:func:`column_agreement`; NaN where the gate is not applied; :data:`COLUMN_Z`).
    base : str
        The structured model the map is built on: the chosen one, or the one the pixel model shrinks
        toward (its column or row gains are in the written k either way).
    """

    k: np.ndarray
    chosen: str
    scores: dict = field(default_factory=dict)
    split: dict = field(default_factory=dict)
    calibration: Calibration | None = None
    sigma: np.ndarray | None = None  # with a calibration: the predicted standard error of k
    column_agreement: float = float("nan")
    base: str = "none"


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
                 sigma_calibrated: bool = False, measured: "Measured | None" = None) -> FPNModel:
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
    measured : Measured, optional
        What :func:`measure` found of this plane with its halves (its calibration perhaps pooled with
        other planes'): used instead of ``halves`` and ``calibration``, not measured again.
    """
    if force is not None and force not in MODELS:
        raise ValueError(f"force must be one of {', '.join(MODELS)}, got {force!r}")
    # float32 maps (frame-sized: 48 MB each at 12 MP), float64 sums
    k = np.asarray(k, np.float32)
    confidence = np.asarray(confidence, np.float32)
    est = confidence > 0
    sigma = _sigma(confidence)
    if measured is not None:
        fit, strayed, calibration = measured.fit, measured.strayed, measured.calibration
    elif halves is not None:
        fit, strayed, calibration = _measured(k, sigma, est, halves, calibration)
    else:  # the column models' gate only where k's error is measured (see COLUMN_Z)
        fit = _Fits.of(k, sigma, est, gate=calibration is not None and calibration.measured)
        strayed = None
    if calibration is not None:
        sigma = calibration.sigma(sigma)
        if strayed is not None:
            sigma = np.sqrt(sigma**2 + strayed)
        fit = _Fits.of(k, sigma, est, gate=calibration.measured)
    elif strayed is not None:  # halves too few pixels to measure anything: as without them
        fit = _Fits.of(k, sigma, est, gate=False)
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
    chosen = force or min(fit.allowed, key=lambda m: scores[m])
    written_sigma = None
    if chosen == "pixel":
        model_k = np.where(est, fit.base + shrink * deviation, np.float32(1))
        if calibration is not None:  # the posterior's, and the base's own error where it is not shrunk away
            written_sigma, base = np.sqrt(shrink) * np.where(est, sigma, 0), base_variance(fit.best, halves, est)
            if base > 0:
                written_sigma = np.sqrt(written_sigma**2 + (1 - shrink) ** 2 * np.float32(base))
            written_sigma = np.where(est, written_sigma, np.float32(np.inf))
    else:  # a structured model knows every pixel of a column / row parity it has seen
        model_k = fit.full(chosen)
        written_sigma = None if calibration is None else sigma  # without halves an upper bound
        if calibration is not None and (chosen == "none" or halves is not None):  # k errs by the pixel FPN it
            # leaves (the pixel model's sigma_k as its shrinkage goes to 0), by its gains' error, or the prior's SE
            left = prior if chosen == fit.best else pixel_prior_variance((k - model_k)[est], sigma[est])
            left += base_variance(chosen, halves, est)
            written_sigma = np.where(est, np.float32(np.sqrt(left if left > 0 else calibration.prior_se or 0.0)),
                                     np.float32(np.inf))
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
    return FPNModel(model_k.astype(np.float32), chosen, scores, split, calibration, written_sigma, fit.column_z,
                    chosen if chosen != "pixel" else fit.best)


def base_variance(model: str, halves: Halves | None, est: np.ndarray) -> float:
    """The error variance of the column gains of ``model`` on the plane (``est``): ``var(a - b) / 4`` of
    their fits on the ``halves`` (errors each twice the whole fit's; the pixel FPN averages alike in both),
    times the share of the plane the halves see. 0 without column gains (a row parity's, fitted on half
    the plane, errs far less than two halves' shakes differ in showing it), halves or the pixels their
    calibration asks (:data:`MIN_PARTS` parts)."""
    if halves is None or "column" not in model:
        return 0.0
    both = est & (halves.confidence_a > 0) & (halves.confidence_b > 0)
    if both.sum() < MIN_PARTS * PART_PIXELS:
        return 0.0
    maps = []
    for k_half, confidence in ((halves.k_a, halves.confidence_a), (halves.k_b, halves.confidence_b)):
        sigma = _sigma(np.where(both, confidence, 1))
        gains = _Fits.of(np.asarray(k_half, np.float32), sigma, both, gate=False).full("column")[both]
        maps.append(gains / gains.mean(dtype=np.float64))
    return float(np.mean((maps[0] - maps[1]) ** 2, dtype=np.float64)) / 4 * float(both.sum() / est.sum())


@dataclass(frozen=True)
class Measured:
    """What a plane's halves measure of its full fit (:func:`measure`): the structured models fitted
    with the solver's ``sigma_k``, the variance of the error the full fit has and neither half does
    (:func:`departure`), and the :class:`Calibration` (None where there are too few pixels)."""

    fit: _Fits
    strayed: np.ndarray
    calibration: Calibration | None


def measure(k: np.ndarray, confidence: np.ndarray, halves: Halves) -> Measured:
    """What :func:`select_model` measures of a plane with ``halves``, to pool its calibration with
    other planes' (:func:`pooled_priors`) before the model is chosen with it (``measured=``)."""
    confidence = np.asarray(confidence, np.float32)
    return Measured(*_measured(np.asarray(k, np.float32), _sigma(confidence), confidence > 0, halves))


def _sigma(confidence: np.ndarray) -> np.ndarray:
    """``sigma_k`` of ``confidence``, float32, at least 1e-6 (a weight ``1 / sigma_k^2`` stays finite)."""
    return np.maximum(sigma_from_confidence(confidence), 1e-6).astype(np.float32)


def _measured(k: np.ndarray, sigma: np.ndarray, est: np.ndarray, halves: Halves,
              calibration: Calibration | None = None) -> tuple:
    """:class:`Measured`'s fields (``calibration`` kept where one is given)."""
    fit = _Fits.of(k, sigma, est)  # with the column models' gate: k's error is measured (see COLUMN_Z)
    strayed = departure(k, halves, est)
    if calibration is None:  # measured about the solver's own sigma_k's base
        calibration = calibrate(k, sigma, halves, fit.base, est & (strayed == 0))
    return fit, strayed, calibration


#: The planes' measured priors are pooled when their scatter about the pooled one is within chance at
#: this level (chi-square over the planes, with each prior's standard error).
POOL_P = 0.01


def pooled_priors(calibrations: dict) -> dict:
    """The planes' calibrations (name -> :class:`Calibration` or None) with one pixel FPN prior: the
    mean of the measured priors where they agree to within their standard errors (:data:`POOL_P`),
    else the mean of the lowest that agree, and each plane above those its excess counted as
    k's error (``Calibration.shared``). (Not weighted by the standard errors: they grow with the prior
    itself, and weighting by them pulled the mean down, 0.79 % for a true 1.00 % on that burst.)

    A colour filter changes a photosite's response, not the spread of its gains by much; where a
    plane's k is mostly noise its prior is measured to no better than about 30 % (a dark 9-frame RGGB
    burst: 0.61-1.24 % for a true 1.00 % on the four planes), and the written sigma_k of a pixel model
    is about that prior itself. A plane whose prior reads higher than the others' beyond chance holds
    an error both halves share over the whole plane, which no part of its sigma_k stands out by
    (interpolating a fine texture, worst on red and blue, whose samples are twice as far apart as the
    greens'): on a 9-frame RGGB burst of the photograph `brick` at a 7.5 % mean level the red and blue
    priors read 2.19 / 2.04 % and the greens' 1.22 / 1.24 % for a true 1.00 %, and trusting them wrote
    a map 0.888x of no correction (1.006x so). A sensor whose colours' gains do spread differently
    gets the lowest spread's shrinkage on every plane: less correction, not a worse one."""
    measured = {name: c for name, c in calibrations.items()
                if c is not None and c.measured and c.prior is not None and c.prior_se is not None
                and np.isfinite(c.prior_se) and c.prior_se > 0}
    if len(measured) < 2:
        return calibrations
    group = list(measured)
    if not _agree(measured, group):  # the lowest that agree, taken from the lowest up
        ranked = sorted(measured, key=lambda name: measured[name].prior)
        group = ranked[:1]
        for name in ranked[1:]:
            if not _agree(measured, group + [name]):
                break
            group.append(name)
    pooled = max(float(np.mean([measured[name].prior for name in group])), 0.0)
    se = float(np.sqrt(sum(measured[name].prior_se ** 2 for name in group))) / len(group)
    return {name: dataclasses.replace(c, prior=pooled, prior_se=se,
                                      shared=0.0 if name in group else max(c.prior - pooled, 0.0))
            if name in measured else c for name, c in calibrations.items()}


def _agree(measured: dict, names: list) -> bool:
    """Whether the priors of the planes ``names`` agree about their plain mean within chance: chi-square's
    1 - :data:`POOL_P` quantile with n - 1 degrees of freedom (a little above chi-square where the errors
    differ, so the test refuses somewhat more often than POOL_P)."""
    if len(names) < 2:
        return True
    prior = np.array([measured[name].prior for name in names])
    se = np.array([measured[name].prior_se for name in names])
    return float(np.sum(((prior - prior.mean()) / se) ** 2)) <= chi2_quantile(1 - POOL_P, len(names) - 1)


@dataclass(frozen=True)
class _Fits:
    """The structured models fitted to k with weights ``1 / sigma^2``: each a gain per (row parity,
    column) with its parameters beyond the overall scale (which the gauge fixes), their AIC, the
    column and row parts of ``column+row``, the best one's map (``base``), the column gains'
    agreement between the plane's top and bottom (:func:`column_agreement`) and the models it
    allows (the column ones only at :data:`COLUMN_Z` or more)."""

    sums: _Sums
    fits: dict
    scores: dict
    col: np.ndarray
    row: np.ndarray
    best: str
    base: np.ndarray
    column_z: float
    allowed: tuple

    @classmethod
    def of(cls, k: np.ndarray, sigma: np.ndarray, est: np.ndarray, *, gate: bool = True) -> "_Fits":
        weight = np.where(est, np.float32(1) / sigma**2, np.float32(0))
        sums = _Sums.of(k, weight)
        column_z = column_agreement(k, weight) if gate else float("nan")
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
        allowed = [m for m in fits if "column" not in m or not column_z < COLUMN_Z]  # NaN: not measurable
        best = min(allowed, key=lambda m: scores[m])
        base = np.broadcast_to(fits[best][0].astype(np.float32), (2, w))[parity]
        return cls(sums, fits, scores, col, row, best, base, column_z, tuple(allowed) + ("pixel",))

    def full(self, model: str) -> np.ndarray:
        """The structured ``model``'s map, frame-sized."""
        parity = np.arange(self.base.shape[0]) % 2
        return np.broadcast_to(self.fits[model][0].astype(np.float32), (2, self.base.shape[1]))[parity]


#: The column gains fitted on the plane's top and bottom halves apart must agree (:func:`column_agreement`)
#: by at least this many standard errors for a column model to be a candidate, on a plane whose k's
#: error is measured (two halves of the frames). Measured (240x320 8-bit, 3 % pixel FPN): 1.3 / 0.4 with
#: no column FPN, 3.4 / 4.3 with 0.2 %, 8.6-12.6 with 0.5-4 %; 38 planes of bursts without column FPN
#: -2.7 to 3.0 (docs/method.md section 11). Without halves the gate is not applied (docs/limits.md).
COLUMN_Z = 4.0


def column_agreement(k: np.ndarray, weight: np.ndarray) -> float:
    """How far column gains fitted apart on the top and bottom halves of the rows agree: their
    covariance over the columns both halves see, in standard errors (NaN with fewer than 8 such columns).

    A sensor's column FPN is the same down the whole column, so the halves' gains covary; an error
    that runs along a column (interpolating the scene's vertical edges) does not reach from one half
    to the other. AIC counts the pixels as independent and cannot tell the two apart."""
    half = k.shape[0] // 4 * 2  # an even row: both halves hold both row parities alike
    gains, seen = [], True
    for rows in (slice(0, half), slice(half, None)):
        total = weight[rows].sum(axis=0, dtype=np.float64)
        wk = (weight[rows] * k[rows]).sum(axis=0, dtype=np.float64)  # float32 product: half a plane at a time
        gains.append(np.divide(wk, total, out=np.zeros_like(total), where=total > 0))
        seen = seen & (total > 0)
    if seen.sum() < 8:
        return float("nan")
    cov, variance = covariance(gains[0][seen], gains[1][seen])
    se = np.sqrt(variance)
    return cov / se if se > 0 else float("nan")


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
