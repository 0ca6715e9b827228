"""Stuck photosites: readings that stay at one value while a healthy photosite's would vary with
the scene along its trajectory and the noise (:mod:`solve.defects`, which finds the other kinds)."""

from __future__ import annotations

import numpy as np

from ..metrics import MAD_TO_SIGMA
from .predict import ring_median
from .stacks import each_strip

#: Readings whose RMS spread over the frames is below this fraction of a healthy photosite's are stuck.
STUCK_SPREAD = 0.02
#: ... tested only where a healthy one's is above this many quantisation steps (RMS) at 8 frames or
#: fewer: with less, a healthy photosite often reads one count in every frame.
QUANTISED_STEPS = 3.0
#: With more frames, from the RMS (in steps) at which a healthy photosite reads one value in every
#: frame by this chance: that of QUANTISED_STEPS at 8 frames (readings rounded from a normal
#: spread, the worst offset of its mean from a step).
ONE_VALUE_CHANCE = 2.5e-7


def stuck_photosites(frames: np.ndarray, read: np.ndarray, whole: np.ndarray, x: np.ndarray, typical: float,
                     noise, step: float, floor: float, threads: int = 1) -> np.ndarray:
    """Photosites whose readings (unsaturated and following the motion in every frame) vary far
    less than a healthy one's would, where that is well past quantisation. A healthy one's
    variance is the smaller of two estimates, each too large somewhere: the median of its 8
    neighbours' (too large beside an edge) and the scene's along its trajectory plus the noise
    at its level (the noise model takes in the prediction's error on aliased planes). And that
    read one value, to a quantisation step, in every frame: beside an edge the prediction misses
    (a border) both estimates can be far too large for a healthy photosite, whose readings still
    vary by its temporal noise. ``read`` are the ``frames`` as read (before the exposures were
    divided out), where a stuck photosite's readings are one value; ``whole``, the photosites whose
    every reading is usable (not saturated, following the motion, predicted). One value at or below
    ``floor`` (about black) where the scene predicted along the trajectory is too (its median) is
    not tested: a healthy photosite in a black region reads it too, and beside a bright edge both
    estimates of its variance are far too large (on a 240x320 RGGB `astronaut` burst at 75 %, 75
    of 76 800 photosites were flagged so). The variance over the frames a strip at a time on
    ``threads`` threads."""
    stuck = np.zeros(whole.shape, bool)
    at = np.nonzero(whole & (np.ptp(read, axis=0) <= step))  # the few that read one value: tested further
    if not at[0].size:
        return stuck
    variance = np.empty(whole.shape, np.float32)

    def over_frames(rows):  # a strip's temporaries, not the stack's
        variance[rows] = frames[:, rows].var(axis=0)

    each_strip(over_frames, read.shape, threads=threads)
    around, _ = ring_median(variance, whole, at)
    spread = read[:, at[0], at[1]].var(axis=0)
    seen = x[:, at[0], at[1]]
    # robust: a prediction gone wrong in one frame (an edge) does not make the scene vary
    middle = np.median(seen, axis=0)
    scene = MAD_TO_SIGMA * np.median(np.abs(seen - middle[None]), axis=0)
    expected = np.fmin(np.nan_to_num(around, nan=np.inf), (typical * scene) ** 2 + noise(np.maximum(middle, 0.0)))
    lit = (read[0][at] > floor) | (middle > floor)
    least = quantised_steps(frames.shape[0]) * step
    stuck[at] = lit & (expected > least**2) & (spread < STUCK_SPREAD**2 * expected)
    return stuck


def one_value_chance(sigma: float, n_frames: int) -> float:
    """The chance that ``n_frames`` readings rounded to whole steps from a normal spread of RMS
    ``sigma`` steps are all one value, at the worse of a mean on a step and between two."""
    from scipy.stats import norm

    half = np.ceil(8 * sigma) + 1
    edges = np.arange(-half, half + 2) - 0.5  # between whole steps, 8 sigmas and more either side
    return max(float(np.sum(np.diff(norm.cdf((edges - mean) / sigma)) ** n_frames)) for mean in (0.0, 0.5))


def quantised_steps(n_frames: int) -> float:
    """The least RMS (in quantisation steps) of a healthy photosite's readings at which one value in
    every frame is a stuck photosite's: :data:`QUANTISED_STEPS` up to 8 frames, with more where a
    healthy one reads one value by no more than :data:`ONE_VALUE_CHANCE` (1.4 at 12 frames, 1.0 at 16)."""
    if n_frames <= 8:
        return QUANTISED_STEPS
    from scipy.optimize import brentq

    return float(brentq(lambda s: one_value_chance(s, n_frames) - ONE_VALUE_CHANCE, 0.05, QUANTISED_STEPS))


def quantisation_step(frames: np.ndarray) -> float:
    """The smallest difference between distinct readings (of a sample): one count of integer
    data, about 0 of continuous data."""
    values = np.unique(frames.ravel()[:: max(1, frames.size // 200_000)])
    steps = np.diff(values)
    return float(steps[steps > 0].min()) if (steps > 0).any() else 0.0
