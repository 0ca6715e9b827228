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
0, 1, W - 1, W and N - 1 (every pixel's own k, which fits exactly). AIC
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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .accurate import sigma_from_confidence
from .metrics import robust_spread

MODELS = ("none", "row", "column", "column+row", "pixel")


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
    """

    k: np.ndarray
    chosen: str
    scores: dict = field(default_factory=dict)
    split: dict = field(default_factory=dict)


def structured_parts(k: np.ndarray, weight: np.ndarray, *, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Column gains ``c`` (W,) and even/odd row gains ``r`` (2,) with ``k ~ c[x] r[y % 2]``.

    Weighted means (weights ``weight``, zero for unestimated pixels),
    alternated ``rounds`` times; both normalised to mean 1 where weighted.
    """
    h, w = k.shape
    parity = np.arange(h) % 2
    col = np.ones(w)
    row = np.ones(2)
    for _ in range(rounds):
        per_row = row.astype(k.dtype)[parity][:, None]
        wsum = weight.sum(axis=0, dtype=np.float64)
        col = np.divide((weight * k / per_row).sum(axis=0, dtype=np.float64), wsum, out=np.ones(w), where=wsum > 0)
        col /= np.average(col, weights=np.maximum(wsum, 1e-300)) if wsum.sum() > 0 else 1.0
        for p in (0, 1):
            sel = parity == p
            wp = weight[sel]
            total = wp.sum(dtype=np.float64)
            row[p] = (wp * k[sel] / col.astype(k.dtype)[None, :]).sum(dtype=np.float64) / total if total > 0 else 1.0
        counts = np.array([weight[parity == p].sum(dtype=np.float64) for p in (0, 1)])
        row /= np.average(row, weights=counts) if counts.sum() > 0 else 1.0
    return col, row


def select_model(k: np.ndarray, confidence: np.ndarray, *, force: str | None = None) -> FPNModel:
    """Pick the model by AIC (or ``force`` one) and report the FPN split.

    Parameters
    ----------
    k, confidence : ndarray, shape (H, W)
        The solver's per-pixel estimate and its confidence
        (:func:`accurate.sigma_from_confidence` gives ``sigma_k`` back).
    force : str, optional
        One of :data:`MODELS` instead of the AIC choice.
    """
    if force is not None and force not in MODELS:
        raise ValueError(f"force must be one of {', '.join(MODELS)}, got {force!r}")
    # float32 maps (frame-sized: 48 MB each at 12 MP), float64 sums
    k = np.asarray(k, np.float32)
    confidence = np.asarray(confidence, np.float32)
    est = confidence > 0
    sigma = np.maximum(sigma_from_confidence(confidence), 1e-6).astype(np.float32)
    weight = np.where(est, np.float32(1) / sigma**2, np.float32(0))
    col, row = structured_parts(k, weight)
    parity = np.arange(k.shape[0]) % 2
    w = k.shape[1]
    fits = {
        # parameters beyond the overall scale, which the gauge fixes for every model
        "none": (np.broadcast_to(np.float32(_weighted_mean(k, weight)), k.shape), 0.0),
        "row": (np.broadcast_to(_rows_only(k, weight)[parity][:, None], k.shape), 1.0),
        "column": (np.broadcast_to(_columns_only(k, weight)[None, :], k.shape), w - 1.0),
        "column+row": (col.astype(np.float32)[None, :] * row.astype(np.float32)[parity][:, None], float(w)),
    }
    scores = {name: _chi2(k, fit, weight) + 2.0 * params for name, (fit, params) in fits.items()}
    # is there pixel FPN at all: every pixel's own k against the best structured model
    scores["pixel"] = 2.0 * max(int(est.sum()) - 1, 0)
    base, _ = fits[min(fits, key=lambda m: scores[m])]
    deviation = np.where(est, k - base, np.float32(0))
    prior = pixel_prior_variance(deviation[est], sigma[est])
    shrink = np.float32(prior) / (np.float32(prior) + sigma**2)
    fits["pixel"] = (np.where(est, base + shrink * deviation, np.float32(1)), 0.0)
    del deviation, shrink
    chosen = force or min(MODELS, key=lambda m: scores[m])
    # a structured model knows every pixel of a column / row parity it has seen
    model_k = np.array(fits[chosen][0], dtype=np.float32)
    if est.any():
        model_k /= model_k[est].mean(dtype=np.float64)
    if chosen == "pixel":
        model_k[~est] = 1.0
    split = {
        "pixel": 100.0 * float(np.sqrt(prior)),
        "column": 100.0 * robust_spread(1.0 / col[weight.sum(axis=0) > 0]) if est.any() else 0.0,
        "row": 100.0 * abs(row[0] - row[1]) / 2.0,
    }
    return FPNModel(model_k.astype(np.float32), chosen, scores, split)


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


def _chi2(k: np.ndarray, fit: np.ndarray, weight: np.ndarray) -> float:
    """``sum weight (k - fit)^2``; ``weight`` is 0 where k was not estimated (k and fit finite there)."""
    return float(np.sum(weight * np.square(k - fit), dtype=np.float64))


def _weighted_mean(k: np.ndarray, weight: np.ndarray) -> float:
    total = weight.sum(dtype=np.float64)
    return float((weight * k).sum(dtype=np.float64) / total) if total > 0 else 1.0


def _rows_only(k: np.ndarray, weight: np.ndarray) -> np.ndarray:
    parity = np.arange(k.shape[0]) % 2
    out = np.ones(2)
    for p in (0, 1):
        total = weight[parity == p].sum(dtype=np.float64)
        out[p] = (weight[parity == p] * k[parity == p]).sum(dtype=np.float64) / total if total > 0 else 1.0
    return out


def _columns_only(k: np.ndarray, weight: np.ndarray) -> np.ndarray:
    wsum = weight.sum(axis=0, dtype=np.float64)
    return np.divide((weight * k).sum(axis=0, dtype=np.float64), wsum, out=np.ones(k.shape[1]), where=wsum > 0)


