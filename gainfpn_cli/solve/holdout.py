"""The hold-out check: does k reduce the brightness-constancy residual between two frames whose
noise it has not seen, by more than the check's own noise?

The map is fitted without the last frame; the check compares that frame with the reference. The
reference was fitted, and a fit learns a little of each fitted frame's noise (about 1 / n of it):
k times the reference is less noisy than the reference, so comparing it flatters k (measured,
12-bit dark bursts of 8 frames: residual ratio 0.85 against 0.98 from two unfitted frames, while
the MSE on an unfitted frame was 1.03x). So the check's k comes from a second fit without the
reference (:func:`solving.check`): neither frame it compares is in it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..geometry.resample import sample, valid_samples
from .accurate import power_of_two_scale

#: Side (px) of the square blocks the residuals are summed over for the jackknife: larger than
#: the interpolation kernel and the solver's 5x5 windows, so blocks are nearly independent.
BLOCK = 16
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
                   regions: dict | None = None, disagreement: np.ndarray | None = None) -> dict[str, Check]:
    """Brightness-constancy residual of the held-out frame against the reference, with k over without
    (the held-out frame brought to the reference's exposure), per grid. ``frames`` hold the reference
    first and the held-out frame last; ``grids`` are :func:`geometry.planes.solve_grids`; ``regions``
    (grid name -> (rows, columns) slices) restricts each grid's check to where its k was fitted;
    ``disagreement`` (frame-shaped, >= 0) leaves out the blocks where it is an outlier (:data:`OUTLIER`)."""
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
        with_k = np.where(valid, kp * ref - sample(kp * held, M, shape), 0.0)
        without = np.where(valid, ref - sample(held, M, shape), 0.0)
        num, den = _block_sums(with_k**2), _block_sums(without**2)
        keep = np.ones(num.shape, bool)
        if disagreement is not None:
            keep = _agreeing(_block_sums(np.where(valid, grid.gather(disagreement), 0.0))
                             / np.maximum(_block_sums(valid), 1), den > 0)
        check = _jackknife(num[keep], den[keep])
        checks[grid.name] = dataclasses.replace(check, left_out=int(np.sum(~keep & (den > 0))))
    return checks


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


def _jackknife(num: np.ndarray, den: np.ndarray) -> Check:
    """``sum num / sum den`` and its delete-one-block jackknife standard error, over the blocks
    that hold any residual; ratio 1 and standard error inf if none does."""
    used = den > 0
    num, den = num[used], den[used]
    total_num, total_den = float(num.sum()), float(den.sum())
    if len(den) < 2 or total_den <= 0:
        return Check(1.0, float("inf"), num, den)
    left_out = (total_num - num) / np.maximum(total_den - den, np.finfo(float).tiny)
    n = len(den)
    se = float(np.sqrt((n - 1) / n * np.sum((left_out - left_out.mean()) ** 2)))
    return Check(total_num / total_den, se, num, den)
