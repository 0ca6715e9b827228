"""k's error measured on two halves of the frames: k fitted again on the even and the odd frames
(:class:`Halves`), the factor that scales the solver's ``sigma_k`` to k's actual error and the
pixel FPN's variance (:class:`Calibration`, :func:`calibrate`), and where the full fit strays from
both halves (:func:`departure`). docs/method.md section 11.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.resample import masked_window_mean
from ..metrics import chi2_quantile
from .result import sigma_from_confidence


@dataclass(frozen=True)
class Halves:
    """k fitted again on two disjoint halves of the frames (before any FPN model), on part of the
    plane: confidence 0 where a half has no estimate. ``monotone``: the error both halves share grows
    with sigma_k (:func:`_shared`); not on a mosaic's colour planes, whose aliasing errs most in flat
    patches, where sigma_k is least."""

    k_a: np.ndarray
    confidence_a: np.ndarray
    k_b: np.ndarray
    confidence_b: np.ndarray
    monotone: bool = True


@dataclass(frozen=True)
class Calibration:
    """What two halves measured (:func:`calibrate`): the factor that scales ``sigma_k`` to k's
    actual error, at the RMS ``sigma_k`` of each decile (between them, interpolated in
    ``log sigma_k``; beyond them, the end ones), and the pixel FPN prior ``s^2`` (None: from the
    deviations) with its standard error (None: not measured). ``measured`` is False for the solver's
    ``sigma_k`` taken as it is (factor 1). ``shared`` is an error variance of every pixel that the
    halves took for pixel FPN (a mosaic plane's prior above the other planes': :func:`fpnmodel.pooled_priors`)."""

    log_sigma: np.ndarray
    factor: np.ndarray
    prior: float | None
    measured: bool = True
    prior_se: float | None = None
    shared: float = 0.0

    def sigma(self, sigma: np.ndarray) -> np.ndarray:
        """``sigma_k`` (the solver's) scaled to k's actual error, ``shared`` added; inf stays inf."""
        sigma = np.asarray(sigma, np.float32)
        finite = np.isfinite(sigma) & (sigma > 0)
        scale = np.interp(np.log(np.where(finite, sigma, 1)), self.log_sigma, self.factor).astype(np.float32)
        scaled = sigma * scale
        if self.shared > 0:
            scaled = np.sqrt(scaled**2 + np.float32(self.shared))
        return np.where(finite, scaled, sigma)


#: Side (px) of the window whose mean sigma_k^2 orders the deciles the pixel FPN is pooled over
#: (:func:`local_sigma2`, :func:`_prior`).
LOCAL_WINDOW = 5


def local_sigma2(sigma: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The mean ``sigma_k^2`` of the other ``mask`` pixels of the :data:`LOCAL_WINDOW` window (the
    pixel's own where there are none). A pixel's own sigma_k falls with its own gain (its readings' information), so its
    deciles would slice the pixel FPN itself where the scene is flat; its neighbours' follow the scene
    and not its gain. (Counting the pixel itself, one of 25, put the pooled pixel FPN variance 2.4-3.7 %
    low on synthetic halves whose sigma_k goes as the gain^-2: tests/test_fpnmodel.py.) k's error does
    follow a pixel's own sigma_k: the calibration's deciles are by that."""
    import cv2

    s2 = np.where(mask, np.asarray(sigma, np.float32) ** 2, np.float32(0))
    ring = np.ones((LOCAL_WINDOW, LOCAL_WINDOW), np.float32)
    ring[LOCAL_WINDOW // 2, LOCAL_WINDOW // 2] = 0  # summed directly: no own value subtracted in float32
    total = cv2.filter2D(s2, -1, ring, borderType=cv2.BORDER_CONSTANT)
    others = cv2.filter2D(mask.astype(np.float32), -1, ring, borderType=cv2.BORDER_CONSTANT)
    # a pixel with no neighbour in the mask keeps its own
    return np.divide(total, others, out=s2.copy(), where=others > 0)


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


#: A part's error beyond the halves' Hausman difference (one they share) is taken in with the weight
#: ``t^2 / (SHARED_T2 + t^2)``, ``t`` the excess over its standard error: half of it at 2 standard errors.
#: Measured on synthetic halves (30 seeds, factors against the truth): with no shared error, 4 % RMS (a
#: hard cut at 3 standard errors: 1 %, full weight: 6.5 %); on a 9-frame camera RGGB burst, whose shared
#: error stands 2-5 standard errors out, the four planes' residual 1.09 % (a hard cut: 1.17 %, without
#: this term 1.19 %; true FPN 1.0 %); both measured with the shared error read per decile of the pixel's
#: own sigma_k and without the chi-square gate (SHARED_P), which now keeps chance out.
SHARED_T2 = 4.0
#: The error the halves share is counted only where the parts' excesses over the pixel FPN scatter more
#: than chance at this level (chi-square, :func:`_shared`).
SHARED_P = 0.01
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


#: A half whose sigma_k at a pixel is over this many times the full fit's has next to no estimate
#: there (a 400th of the full fit's information): its Hausman term ``(k_a - k) (k_b - k)``, of
#: variance ``sigma_a^2 sigma_b^2``, outweighs hundreds of pixels'. Measured on a 16-frame RGGB
#: burst of the photograph `astronaut` at a 7.5 % mean level (docs/bench/confidence.py): six such
#: pixels took a green plane's most precise tenth to a factor of 0.31 (k erred 1.03x the solver's
#: sigma_k; 0.79 without them); a cut at 10 took the blue plane's from 1.26 to 0.31 (k erred 1.37x).
HALF_SIGMA_RATIO = 20.0


def informative(halves: Halves, sigma: np.ndarray) -> np.ndarray:
    """Where both halves estimate k (confidence above 0) with a ``sigma_k`` at most
    :data:`HALF_SIGMA_RATIO` times the full fit's ``sigma``."""
    limit = HALF_SIGMA_RATIO * np.asarray(sigma, np.float32)
    return np.logical_and.reduce([(c > 0) & (sigma_from_confidence(np.asarray(c, np.float32)) <= limit)
                                  for c in (halves.confidence_a, halves.confidence_b)])


def calibrate(k: np.ndarray, sigma: np.ndarray, halves: Halves, base: np.ndarray,
              est: np.ndarray) -> Calibration | None:
    """The :class:`Calibration` that ``halves`` measure of the full fit ``k`` (``sigma`` its
    solver's ``sigma_k``), with ``base`` the structured model the pixel FPN deviates from; None
    where all three fits see too few pixels for :data:`MIN_PARTS` parts of :data:`PART_PIXELS`."""
    both = est & informative(halves, sigma) & np.isfinite(sigma)
    count = min(int(both.sum()) // PART_PIXELS, MAX_PARTS)
    if count < MIN_PARTS:
        return None
    s = sigma[both].astype(np.float64)
    k_full, k_a, k_b = (np.asarray(m, np.float64)[both] for m in (k, halves.k_a, halves.k_b))
    d_full, d_a, d_b = k_full - base[both], k_a - base[both], k_b - base[both]
    parts = np.array_split(np.argsort(s), count)
    order = np.argsort(local_sigma2(sigma, both)[both])
    rows, columns = np.nonzero(both)
    blocks = (rows // SE_BLOCK) * (both.shape[1] // SE_BLOCK + 1) + columns // SE_BLOCK
    inflation = _correlated(d_a, d_b, blocks)
    prior, prior_se = _prior(d_a, d_b, np.array_split(order, count))
    fine, fine_se = _prior(d_a, d_b, np.array_split(order, int(both.sum()) // PART_PIXELS))
    fine_se *= inflation  # the prior's own, for pooling the planes' (fpnmodel.pooled_priors)
    cross = _clipped((k_a - k_full) * (k_b - k_full), parts)
    shared = _shared(d_full, cross, np.array_split(order, count), prior, prior_se, s.size, halves.monotone)
    # and one that runs over several pixels, which the above sees only where it stands out of the FPN's
    # scatter (counted once: the larger of the two)
    shared = np.maximum(shared, _smooth(d_a, d_b, rows, columns, both.shape, blocks, np.array_split(order, count)))
    log_sigma, factor = [], []
    for part in parts:
        square = float(np.mean(s[part] ** 2))
        error = -float(np.mean(cross[part]))  # the Hausman difference: what the halves do not share
        error += float(np.mean(shared[part]))
        log_sigma.append(0.5 * np.log(square))
        factor.append(max(np.sqrt(max(error, 0.0) / square), MIN_FACTOR))
    return Calibration(np.array(log_sigma), np.array(factor), fine, prior_se=fine_se)


#: Each pixel's Hausman term is clipped at this many times the median magnitude of its tenth's
#: (:func:`_clipped`). Where both halves' fits failed on a spot (a half of 4 frames, a bright edge by
#: clipped readings) their terms run to -40 to -260 sigma_k^2: on a 9-frame RGGB burst of the
#: photograph `camera` at a 40 % mean level about ten such pixels took the greens' fourth tenth to
#: the factor's floor (0.1; k erred 0.74x the solver's sigma_k), clipped 0.71 / 0.68. On synthetic
#: halves with independent normal errors the clip takes 0-0.7 % off the factors (tests/test_fpnmodel.py).
HAUSMAN_CLIP = 20.0


def _clipped(cross: np.ndarray, parts) -> np.ndarray:
    """``cross`` clipped within each of ``parts`` at :data:`HAUSMAN_CLIP` times its median magnitude."""
    out = cross.copy()
    for part in parts:
        bound = HAUSMAN_CLIP * float(np.median(np.abs(cross[part])))
        if bound > 0:  # (halves equal to the full fit over most of the part: nothing to scale by)
            out[part] = np.clip(cross[part], -bound, bound)
    return out


def _shared(d_full: np.ndarray, cross: np.ndarray, parts, prior: float, prior_se: float, size: int,
            monotone: bool = True) -> np.ndarray:
    """The variance of the error both halves share, at each pixel: measured over ``parts`` of the
    neighbours' sigma_k (:func:`local_sigma2`), as all of k's error (its deviations' variance, about the
    part's mean) less the pixel FPN's ``prior`` and what the halves do not share (``cross``, the
    Hausman difference's terms). The pixel FPN does not know the scene: it is the same in every part
    of the neighbours' sigma_k, not of the pixel's own (which falls with its own gain, so its deciles
    slice the FPN: -9 to +3 %^2 about 25 %^2 on a smooth 8-bit burst, read as shared error). Counted
    only where the parts scatter about ``prior`` beyond chance (:data:`SHARED_P`): at 5 % pixel FPN a
    part's FPN variance scatters by 0.4 %^2, several times ``sigma_k^2`` of a bright burst's pixels.

    With ``monotone`` the error both halves share is what interpolation makes of the scene's detail,
    which raises the residuals and so ``sigma_k``: it grows with the neighbours' ``sigma_k``, and the
    parts' excesses are fitted so (non-decreasing, weighted by their sampling variances:
    :func:`scipy.optimize.isotonic_regression`), each run of parts pooled to one excess and one standard
    error: a chance high of the FPN's scatter in one part is pooled with the parts beside it. Without,
    each part's is its own: on a mosaic's colour plane aliasing errs most in flat patches, and pooled, a
    shared error of 3x sigma_k on the most precise tenth is spread over every tenth (tests/test_fpnmodel.py)."""
    from scipy.optimize import isotonic_regression

    shared = np.zeros(size)
    excesses, variances = [], []
    for part in parts:
        beyond = (d_full[part] - d_full[part].mean()) ** 2 + cross[part]
        excesses.append(float(np.mean(beyond)) - prior)
        variances.append(max(float(np.var(beyond)) / len(part) + prior_se**2, np.finfo(float).tiny))
    excesses, variances = np.array(excesses), np.array(variances)
    # chi-square's 1 - SHARED_P quantile with one degree of freedom per part
    if not np.sum(excesses**2 / variances) > chi2_quantile(1 - SHARED_P, len(parts)):
        return shared
    runs, blocks = excesses, np.arange(len(parts) + 1)  # without monotone, each part a run of its own
    if monotone:
        fit = isotonic_regression(excesses, weights=1.0 / variances)
        runs, blocks = fit.x, fit.blocks
    for start, stop in zip(blocks[:-1], blocks[1:]):
        excess, weights = float(runs[start]), variances[start:stop].min() / variances[start:stop]  # scaled to <= 1
        # the run's weighted mean's variance: its parts' own pooled, the prior's (in every part alike) not
        t2 = excess**2 / (float(np.sum(weights**2 * (variances[start:stop] - prior_se**2))) / float(weights.sum()) ** 2
                          + prior_se**2)
        for part in parts[start:stop]:
            shared[part] = max(excess, 0.0) * t2 / (SHARED_T2 + t2)  # taken in as far as it stands out of its noise
    return shared


#: Distance (px, Chebyshev) at which :func:`_smooth` reads the error the halves share: past the reach
#: of a kernel's spreading of one photosite's gain into its neighbours' k.
LAG = 2


def _smooth(d_a: np.ndarray, d_b: np.ndarray, rows: np.ndarray, columns: np.ndarray, shape, blocks: np.ndarray,
            parts) -> np.ndarray:
    """The variance of an error both halves share that runs over several pixels, at each pixel: per
    part (as :func:`_shared`'s), the mean product of one half's deviation with the other's :data:`LAG`
    px away (over the ring of offsets at that distance), clipped as the Hausman terms are.

    The pixel FPN is the same in both halves but independent from one photosite to the next, and
    their noise is independent, so neither enters it; an error the halves share that the fit spreads
    over flat patches (a colour plane's aliasing) does, which :func:`_shared` reads only where it
    stands out of the parts' scatter about the FPN. On a 640x480 12-bit RGGB dead-leaves burst of 16
    frames (seed 1) the blue plane's most precise tenth, all in flat patches, erred 1.45x its written
    sigma_k (0.18 % of its 0.39 % in a 3 px low-pass, a green plane's 0.07 %). Counted as
    :func:`_shared` counts its excess: where the parts' means stand out of their block-jackknife
    standard errors beyond chance (:data:`SHARED_P`), each as far as it does. A pixel FPN with
    structure at this distance is read as error too: less correction, not a worse one."""
    import cv2

    b, seen = np.zeros(shape), np.zeros(shape)
    b[rows, columns], seen[rows, columns] = d_b - d_b.mean(), 1.0
    ring = np.ones((2 * LAG + 1, 2 * LAG + 1))
    ring[1:-1, 1:-1] = 0  # the offsets at distance LAG, as local_sigma2's window
    total, count = (cv2.filter2D(m, -1, ring, borderType=cv2.BORDER_CONSTANT)[rows, columns] for m in (b, seen))
    lagged = np.divide((d_a - d_a.mean()) * total, count, out=np.zeros(count.shape), where=count > 0)
    lagged = _clipped(lagged, parts)
    smooth = np.zeros(lagged.size)
    means, t2s = [], []
    for part in parts:
        mean = float(np.mean(lagged[part]))
        means.append(mean)
        t2s.append(mean**2 / max(_jackknife_variance(lagged[part], blocks[part]), np.finfo(float).tiny))
    if not sum(t2s) > chi2_quantile(1 - SHARED_P, len(t2s)):
        return smooth
    for part, mean, t2 in zip(parts, means, t2s):
        smooth[part] = max(mean, 0.0) * t2 / (SHARED_T2 + t2)
    return smooth


def _jackknife_variance(values: np.ndarray, blocks: np.ndarray) -> float:
    """The sampling variance of the mean of ``values``, by deleting one of ``blocks`` at a time (the
    formula's for independent values where there are fewer than :data:`MIN_BLOCKS`)."""
    sums, sizes = np.bincount(blocks, values), np.bincount(blocks)
    sums, sizes = sums[sizes > 0], sizes[sizes > 0]
    if sizes.size < MIN_BLOCKS:
        return float(np.var(values)) / values.size
    left_out = (sums.sum() - sums) / (sizes.sum() - sizes)
    return (sizes.size - 1) / sizes.size * float(np.sum((left_out - left_out.mean()) ** 2))


#: Fewest blocks a jackknife deletes one at a time (:func:`_jackknife_variance`).
MIN_BLOCKS = 8
#: Side (plane px) of the blocks :func:`_correlated` deletes one at a time: k's errors are correlated
#: over a few pixels (the interpolation kernels'), not over 8.
SE_BLOCK = 8


def _correlated(d_a: np.ndarray, d_b: np.ndarray, blocks: np.ndarray) -> float:
    """How much larger the standard error of the halves' covariance is than :func:`covariance` gives
    it for independent pixels (at least 1): the delete-one-block jackknife's over the formula's.

    Neighbouring pixels' errors are correlated, so the formula's is too small (measured on a dark
    RGGB burst: the four planes' priors scattered by about twice the standard error it gave)."""
    if np.count_nonzero(np.bincount(blocks)) < MIN_BLOCKS:
        return 1.0
    jackknife = _jackknife_variance((d_a - d_a.mean()) * (d_b - d_b.mean()), blocks)
    _, formula = covariance(d_a, d_b)
    return max(1.0, float(np.sqrt(jackknife / formula))) if formula > 0 else 1.0


def _prior(d_a: np.ndarray, d_b: np.ndarray, parts) -> tuple[float, float]:
    """The pixel FPN's variance and its standard error: the covariance of the halves' deviations,
    pooled over the parts (deciles of sigma_k) that agree with it.

    An error both halves share (interpolating a sharp scene) enters their covariance too, most where
    sigma_k is large; the pixel FPN does not know the scene and is the same in every part. The parts
    are taken from the most precise on, each one whose covariance is not above the pooled one by more
    than :data:`PRIOR_Z` standard errors, and pooled with the inverse of their sampling variances
    (:func:`covariance`'s, for independent pixels). Where neighbours' errors are correlated those
    are too small (:func:`_correlated`) and parts are left out for chance highs: on noise-dominated
    synthetic halves whose errors spread over 3x3 pixels the prior reads 37 % low. Scaled by the
    correlation, the shared error of a dark RGGB burst's red and blue planes (its `chelsea`, 7.5 %,
    9 frames) went into their prior instead (1.37 / 1.51 % for a true 1.00 %), so it is not."""
    covs, variances = [], []
    for part in parts:
        cov, variance = covariance(d_a[part], d_b[part])
        covs.append(cov)
        variances.append(max(variance, np.finfo(float).tiny / len(part)))
    pooled, weight = 0.0, 0.0
    for j in np.argsort(variances):
        if weight > 0 and covs[j] - pooled > PRIOR_Z * np.sqrt(variances[j] + 1.0 / weight):
            continue
        pooled = (pooled * weight + covs[j] / variances[j]) / (weight + 1.0 / variances[j])
        weight += 1.0 / variances[j]
    return max(pooled, 0.0), float(1.0 / np.sqrt(weight))


def covariance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The covariance of ``a`` and ``b`` about their means, and its sampling variance
    ``(var(a) var(b) + cov^2) / n`` (that of normal data)."""
    a, b = a - a.mean(), b - b.mean()
    cov = float(np.mean(a * b))
    return cov, (float(np.mean(a * a) * np.mean(b * b)) + cov**2) / a.size
