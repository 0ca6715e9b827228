"""Stuck photosites: readings that stay at one value while a healthy photosite's would vary with
the scene along its trajectory and the noise (:mod:`solve.defects`, which finds the other kinds)."""

from __future__ import annotations

import numpy as np

from ..metrics import MAD_TO_SIGMA
from .predict import ring_median
from .stacks import each_strip

#: Readings whose RMS spread over the frames is below this fraction of a healthy photosite's are stuck.
STUCK_SPREAD = 0.02
#: ... tested only where a healthy one's is above this many quantisation steps (RMS): with
#: less, a healthy photosite often reads one count in every frame.
QUANTISED_STEPS = 3.0


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
    stuck[at] = lit & (expected > (QUANTISED_STEPS * step) ** 2) & (spread < STUCK_SPREAD**2 * expected)
    return stuck


def quantisation_step(frames: np.ndarray) -> float:
    """The smallest difference between distinct readings (of a sample): one count of integer
    data, about 0 of continuous data."""
    values = np.unique(frames.ravel()[:: max(1, frames.size // 200_000)])
    steps = np.diff(values)
    return float(steps[steps > 0].min()) if (steps > 0).any() else 0.0
