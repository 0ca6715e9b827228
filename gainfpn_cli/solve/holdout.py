"""The hold-out check: does k reduce the brightness-constancy residual between two frames whose
noise it has not seen, by more than the check's own noise?

The map is fitted without the last frame; the check compares that frame with the reference. The
reference was fitted, and a fit learns a little of each fitted frame's noise (about 1 / n of it):
k times the reference is less noisy than the reference, so comparing it flatters k (measured,
12-bit dark bursts of 8 frames: residual ratio 0.85 against 0.98 from two unfitted frames, while
the MSE on an unfitted frame was 1.03x). So the check's k comes from a second fit without the
reference (:func:`checking.check`): neither frame it compares is in it.

On a CFA's planes the residuals are low-passed (:data:`BLUR`) before they are summed. A plane
sampled every other photosite is aliased, predicting one frame from another leaves an
interpolation error there, and a map fitted to the other frames learns part of the error every
pair makes alike: such a map lowers the raw residual of the held-out pair while it is farther
from the truth than k = 1 (measured, a 12-bit RGGB dead leaves burst, 640x480x8, seed 3: blue
ratio 0.992 +- 0.004 accepted, while `gainfpn evaluate` found gain FPN 0.99 -> 1.70 % and MSE
0.4x). That error sits near the plane's Nyquist frequency; gain FPN and noise are white.
Low-passed, the same map reads 1.05 (rejected), while the true gains still read 0.976 +- 0.002.
A full-resolution plane keeps its raw residuals: there the low-pass costs the check its power
where k's error or the residual is not white (120x160 8-bit bursts of 6 frames: the paper's
block solver with 3 % exposure steps taken as equal, 0.53 +- 0.07 -> 0.99 +- 0.08; an unmasked
moving object, 0.89 +- 0.04 -> 1.00 +- 0.01: maps that left 2.8 % of a 5 % gain FPN and cut the
MSE off the object 5.5x, rejected).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from ..geometry.resample import sample, valid_samples
from .result import sigma_from_confidence
from .tiling import power_of_two_scale

#: Side (px) of the square blocks the residuals are summed over for the jackknife: larger than
#: the interpolation kernel and the solver's 5x5 windows, so blocks are nearly independent.
BLOCK = 16
#: Standard deviation (px of the grid) of the Gaussian a CFA plane's residuals are low-passed with:
#: it keeps 9 % of the amplitude at the grid's Nyquist frequency (where interpolating an aliased
#: plane errs) and 1 / (4 pi 0.7^2) = 16 % of the variance of white gain FPN and noise alike.
#: Measured on the RGGB burst above: 1.0 px also rejects the bad map (1.11) but weakens the true
#: gains' margin, none (0) accepts it.
BLUR = 0.7
#: Pixels whose blurred residual draws at least this share of the Gaussian's weight from valid
#: pixels are checked (the border of the valid region, where zeros would mix in, is left out).
BLUR_SUPPORT = 0.8
#: A block is left out of the check when its mean squared disagreement between the check's k and
#: the written k (in standard errors) is above OUTLIER^2 times the median block's: 3 is the usual
#: outlier rule, and it let no more written maps worse than none through on the 48-burst error-rate
#: set (docs/bench/holdout_check.py rates) while it turned away fewer good ones.
OUTLIER = 3.0


@dataclass(frozen=True)
class Check:
    """The residual with k over without on one grid, its jackknife standard error, and the
    blocks it was summed over."""

    ratio: float
    standard_error: float
    num: np.ndarray  # per block: sum of squared residuals with k
    den: np.ndarray  # ... and without
    left_out: int = 0  # blocks where the check's k disagreed with the written one (OUTLIER)

    def passed(self, z: float) -> bool:
        """The ratio is below 1 by more than ``z`` standard errors."""
        return self.ratio + z * self.standard_error < 1.0


def holdout_checks(frames, excluded, exposures, motion, k, *, grids, saturation: float | None,
                   regions: dict | None = None, disagreement: np.ndarray | None = None,
                   columns=()) -> dict[str, Check]:
    """Brightness-constancy residual of the held-out frame against the reference, with k over without
    (the held-out frame brought to the reference's exposure), per grid. ``frames`` hold the reference
    first and the held-out frame last; ``grids`` are :func:`geometry.planes.solve_grids`; ``regions``
    (grid name -> (rows, columns) slices) restricts each grid's check to where its k was fitted;
    ``disagreement`` (frame-shaped, >= 0) leaves out the blocks where it is an outlier (:data:`OUTLIER`);
    ``columns`` names the grids whose maps have a gain per column of the frame (their FPN model's): their
    standard error is the larger of the blocks' jackknife and the one leaving out a column of blocks
    at a time (:func:`column_strips`)."""
    checks = {}
    sat = np.inf if saturation is None else saturation
    scale = np.float32(power_of_two_scale(frames[0]))  # about 1: k times a frame stays far from float32's limits
    for grid in grids:
        ref, held, kp = grid.gather(frames[0]), grid.gather(frames[-1]), grid.gather(k)
        ref_ok, held_ok = (ref > 0) & (ref < sat), (held > 0) & (held < sat)
        if excluded is not None:
            ref_ok &= ~grid.gather(np.broadcast_to(excluded[0, ..., None], frames.shape[1:]))
            held_ok &= ~grid.gather(np.broadcast_to(excluded[-1, ..., None], frames.shape[1:]))
        ref, held = ref / scale, held / (scale * np.float32(exposures[-1]))
        shape = ref.shape
        M = motion.conjugate(grid.S).pair(0, len(frames) - 1, (0, 0) + shape)
        valid = valid_samples(held_ok, M, shape) & ref_ok
        if regions is not None:
            inside = np.zeros(shape, bool)
            inside[regions[grid.name]] = True
            valid &= inside
        with_k = np.where(valid, kp * ref - sample(kp * held, M, shape), np.float32(0))
        without = np.where(valid, ref - sample(held, M, shape), np.float32(0))
        if sparse(grid):
            with_k, without, valid = _low_passed(with_k, without, valid)
        num, den = _block_sums(with_k**2), _block_sums(without**2)
        keep = np.ones(num.shape, bool)
        if disagreement is not None:
            keep = _agreeing(_block_sums(np.where(valid, grid.gather(disagreement), 0.0))
                             / np.maximum(_block_sums(valid), 1), den > 0)
        strips = column_strips(grid, shape)[keep] if grid.name in columns else None
        check = _jackknife(num[keep], den[keep], strips)
        checks[grid.name] = dataclasses.replace(check, left_out=int(np.sum(~keep & (den > 0))))
    return checks


def sparse(grid) -> bool:
    """Whether ``grid`` samples fewer points than the photosites (a CFA's colour planes and its greens'
    lattice): the check low-passes its residuals (:data:`BLUR`)."""
    return abs(float(np.linalg.det(np.asarray(grid.S)[:2, :2]))) > 1.5


def _low_passed(with_k: np.ndarray, without: np.ndarray, valid: np.ndarray):
    """Both residual maps low-passed (:data:`BLUR`), and the pixels where that took enough of its
    weight from valid pixels (:data:`BLUR_SUPPORT`); zero elsewhere. Only the bounding box of
    ``valid`` is filtered (the check's regions are a small part of a large frame)."""
    if not valid.any():
        return with_k, without, valid
    rows, columns = (np.flatnonzero(valid.any(axis=axis)) for axis in (1, 0))
    box = (slice(rows[0], rows[-1] + 1), slice(columns[0], columns[-1] + 1))
    support = np.zeros(valid.shape, bool)
    support[box] = valid[box] & (gaussian_filter(valid[box].astype(np.float32), BLUR, mode="constant") >= BLUR_SUPPORT)
    out = []
    for residual in (with_k, without):
        smooth = np.zeros(residual.shape, np.float32)
        smooth[box] = gaussian_filter(residual[box].astype(np.float32), BLUR, mode="constant")
        out.append(np.where(support, smooth, np.float32(0)))
    return out[0], out[1], support


def pooled(checks) -> Check:
    """One check over all the grids' blocks."""
    checks = list(checks)
    return _jackknife(np.concatenate([c.num for c in checks]), np.concatenate([c.den for c in checks]))


def _agreeing(disagreement: np.ndarray, used: np.ndarray) -> np.ndarray:
    """The blocks whose mean disagreement is at most :data:`OUTLIER` ^ 2 times the median of the
    ``used`` blocks'."""
    if not used.any():
        return np.ones(disagreement.shape, bool)
    return disagreement <= OUTLIER**2 * np.median(disagreement[used])


def _block_sums(a: np.ndarray) -> np.ndarray:
    """Sums over :data:`BLOCK` x :data:`BLOCK` blocks (the last ones smaller), flattened."""
    h, w = a.shape
    rows = np.add.reduceat(a.astype(np.float64), np.arange(0, h, BLOCK), axis=0)
    return np.add.reduceat(rows, np.arange(0, w, BLOCK), axis=1).ravel()


def column_strips(grid, shape: tuple[int, int]) -> np.ndarray:
    """Per block of :func:`_block_sums` over a ``shape`` grid, the strip of the frame's columns it lies
    in: strips as wide as a block is in frame pixels, the block's centre deciding (a CFA's green
    lattice is rotated, so a strip holds blocks of several of its columns). A column FPN model's
    gains are the same down a column, so their error makes the blocks of a column alike, which
    the blocks' jackknife takes for independent draws (the guard's aliased RGGB burst of seed 5,
    docs/limits.md: red's ratio 0.9981 is 2.1 blocks' standard errors below 1, 1.1 of the columns')."""
    h, w = shape
    y, x = np.meshgrid(np.arange(0, h, BLOCK) + BLOCK / 2, np.arange(0, w, BLOCK) + BLOCK / 2, indexing="ij")
    S = np.asarray(grid.S, float)
    frame_x = S[0] @ np.stack([x.ravel(), y.ravel(), np.ones(x.size)])
    return np.floor(frame_x / (BLOCK * np.sqrt(abs(np.linalg.det(S[:2, :2]))))).astype(int)


def _jackknife(num: np.ndarray, den: np.ndarray, groups: np.ndarray | None = None) -> Check:
    """``sum num / sum den`` and its delete-one-block jackknife standard error, over the blocks
    that hold any residual; ratio 1 and standard error inf if none does. With ``groups`` (a label
    per block) the standard error is the larger of that and the delete-one-group jackknife's (inf
    with one group)."""
    used = den > 0
    num, den = num[used], den[used]
    total_num, total_den = float(num.sum()), float(den.sum())
    if len(den) < 2 or total_den <= 0:
        return Check(1.0, float("inf"), num, den)
    se = _delete_one(num, den, total_num, total_den)
    if groups is not None:
        _, group = np.unique(groups[used], return_inverse=True)
        se = max(se, _delete_one(np.bincount(group, num), np.bincount(group, den), total_num, total_den)
                 if group.max() > 0 else float("inf"))
    return Check(total_num / total_den, se, num, den)


def _delete_one(num: np.ndarray, den: np.ndarray, total_num: float, total_den: float) -> float:
    """The jackknife standard error of ``total_num / total_den`` leaving out one entry at a time."""
    left_out = (total_num - num) / np.maximum(total_den - den, np.finfo(float).tiny)
    n = len(den)
    return float(np.sqrt((n - 1) / n * np.sum((left_out - left_out.mean()) ** 2)))


def disagreement(k_check, confidence_check, k, confidence, *, calibrated: bool) -> np.ndarray:
    """``(k_check - k)^2``, in the two maps' combined variance where their confidence is a standard
    error (``calibrated``; the paper's block solver has none); 0 where either is unestimated."""
    both = (confidence_check > 0) & (confidence > 0)
    squared = np.where(both, k_check - k, np.float32(0)) ** 2
    if calibrated:
        variance = sigma_from_confidence(np.where(both, confidence_check, 1)) ** 2 \
            + sigma_from_confidence(np.where(both, confidence, 1)) ** 2
        squared = np.where(both, squared / np.maximum(variance, np.float32(1e-12)), np.float32(0))
    return squared
