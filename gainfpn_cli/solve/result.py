"""What a solver hands on: a plane's k and confidence, and the rules every solver's result obeys.

``confidence`` means one thing: ``1 / (1 + (sigma_k / CONFIDENCE_SCALE)^2)`` for the accurate
solver, whose ``sigma_k`` is a predicted standard error; the paper's block solver, which has
none, gives 1 (solved cleanly), 0.5 (extra regularisation) or 0. Either way 0 is unestimated
(k = 1). :func:`physical` is the one clamp of k to the gain range with the gauge kept.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class GainResult:
    """Gain map of one plane and how it was obtained.

    Attributes
    ----------
    k : ndarray of float32, shape (H, W)
        Correction (multiply to correct); 1.0 where unestimated; mean 1 over
        estimated pixels.
    confidence : ndarray of float32, shape (H, W)
        See the module: 0 where unestimated.
    stats : PaperStats, AccurateStats, SceneStats or None
        What the solver counted on the way.
    offsets : ndarray of float32, shape (H, W), or None
        The scene solver's score of an offset in each pixel's readings besides its gain
        (:func:`solve.scene.offset_scores`; about N(0, 1) for a healthy pixel); None from the others.
    """

    k: np.ndarray
    confidence: np.ndarray
    stats: PaperStats | AccurateStats | SceneStats | None = None
    offsets: np.ndarray | None = None


@dataclass(frozen=True)
class PaperStats:
    """The paper's block solver's counts: blocks solved, those that needed extra regularisation
    and those left unestimated, unestimated pixels, frames that did not move (left out), and
    constraint rows over all blocks."""

    blocks: int
    regularised: int
    unestimated_blocks: int
    unestimated_pixels: int
    static_frames: int
    rows: int

    method = "paper"


@dataclass(frozen=True)
class AccurateStats:
    """The accurate solver's counts: tiles, each tile's GMRES iterations, unestimated pixels
    (of which ``out_of_range_pixels`` had a k outside the gain range) and the median confidence
    of the estimated ones."""

    tiles: int
    gmres_iterations: tuple[int, ...]
    unestimated_pixels: int
    out_of_range_pixels: int
    median_confidence: float

    method = "accurate"


@dataclass(frozen=True)
class SceneStats:
    """The scene solver's counts: tiles, each tile's conjugate-gradient iterations over its
    Gauss-Newton steps, unestimated pixels (of which ``out_of_range_pixels`` had a k outside the
    gain range) and the median confidence of the estimated ones."""

    tiles: int
    cg_iterations: tuple[int, ...]
    unestimated_pixels: int
    out_of_range_pixels: int
    median_confidence: float

    method = "scene"


def stats_from_json(method: str, data: dict) -> PaperStats | AccurateStats | SceneStats:
    """The stats of ``method`` from a dict holding (at least) their fields."""
    cls = {"paper": PaperStats, "accurate": AccurateStats, "scene": SceneStats}[method]
    values = {f.name: data[f.name] for f in fields(cls)}
    for name in ("gmres_iterations", "cg_iterations"):
        if name in values:
            values[name] = tuple(values[name])
    return cls(**values)


#: Predicted standard error of k at which confidence is 0.5.
CONFIDENCE_SCALE = 0.01


def sigma_from_confidence(confidence: np.ndarray) -> np.ndarray:
    """Invert ``confidence = 1 / (1 + (sigma_k / CONFIDENCE_SCALE)^2)``: inf where confidence is 0."""
    confidence = np.asarray(confidence)
    dtype = np.float32 if confidence.dtype == np.float32 else np.float64  # float32 maps stay float32
    ratio = np.divide(dtype(1), confidence, out=np.full(confidence.shape, np.inf, dtype), where=confidence > 0)
    return dtype(CONFIDENCE_SCALE) * np.sqrt(ratio - dtype(1))


def confidence_from_sigma(sigma: np.ndarray) -> np.ndarray:
    """``1 / (1 + (sigma_k / CONFIDENCE_SCALE)^2)``: 0 where ``sigma_k`` is inf."""
    sigma = np.asarray(sigma)
    dtype = np.float32 if sigma.dtype == np.float32 else np.float64
    return (dtype(1) / (dtype(1) + (sigma / dtype(CONFIDENCE_SCALE)) ** 2)).astype(dtype)


def regauge(k: np.ndarray, est: np.ndarray, *, everywhere: bool = True) -> None:
    """The gauge, in place: divide ``k`` (over every pixel, or only ``est`` without ``everywhere``)
    by its mean over the estimated pixels ``est``, so that it is 1 there (docs/method.md section 2)."""
    k[np.ones(k.shape, bool) if everywhere else est] /= k[est].mean(dtype=np.float64)


def out_of_range(k: np.ndarray, est: np.ndarray, gain_range: tuple[float, float]) -> np.ndarray:
    """The estimated pixels whose k is not physical: outside ``gain_range``."""
    low, high = gain_range
    return est & ((k < low) | (k > high))


def physical(result: GainResult, gain_range: tuple[float, float], structured: bool = False) -> GainResult:
    """``result`` with every estimated k in ``gain_range`` and the gauge (mean 1 over the
    estimated pixels) kept: a renormalisation can push a k just past a limit, so pixels
    past it are left unestimated (k = 1, confidence 0) until none is. A ``structured``
    map also gives unestimated pixels their column / row gain, renormalised with the rest."""
    k = np.array(result.k, np.float32)
    confidence = np.array(result.confidence, np.float32)
    while True:  # each round leaves at least one more pixel unestimated
        est = confidence > 0
        outside = out_of_range(k, est, gain_range)
        if not outside.any():
            break
        est &= ~outside
        if est.any():
            regauge(k, est, everywhere=structured)
        k[outside], confidence[outside] = 1.0, 0.0
    return GainResult(k.astype(np.float32), confidence.astype(np.float32), result.stats, result.offsets)
