"""A reading's temporal noise against its level, measured on the burst itself (the defect search's
scatter of each photosite about the scene predicted from the other frames, :mod:`solve.defects`)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..metrics import chi2_quantile
from .stacks import each_strip


@dataclass(frozen=True)
class NoiseModel:
    """A reading's noise variance ``v = c0 + c1 level`` (read and shot noise), in the readings' units."""

    c0: float
    c1: float

    def __call__(self, level) -> np.ndarray:
        return self.c0 + self.c1 * np.asarray(level, np.float64)

    def scaled(self, unit: float) -> NoiseModel:
        """The model of the same readings multiplied by ``unit``."""
        return NoiseModel(self.c0 * unit * unit, self.c1 * unit)

    def level_at_snr(self, snr: float) -> float:
        """The level whose reading is ``snr`` times its noise (RMS): ``snr^2 v(L) = L^2`` solved for L."""
        a = 1.0 / snr**2
        return float((self.c1 + np.sqrt(self.c1**2 + 4.0 * a * self.c0)) / (2.0 * a))


#: A model of no noise: what :func:`fit` gives when no level bin has enough photosites.
SILENT = NoiseModel(0.0, 0.0)


def fit(level: np.ndarray, scatter: np.ndarray, n: int) -> NoiseModel:
    """The :class:`NoiseModel` fitted to the quietest quarter of the photosites in each of 8 level bins:
    their scatter about the predicted scene is the noise with the least prediction error on top.
    ``scatter`` is each photosite's variance about the scene, from ``n - 1`` degrees of freedom,
    ``level`` its mean scene level."""
    quarter = chi2_quantile(0.25, n - 1) / (n - 1)  # lower quartile of a variance estimate, in variances
    edges = np.quantile(level, np.linspace(0, 1, 9))
    centres, values = [], []
    for lo, hi in pairwise(edges):
        inside = (level >= lo) & (level <= hi)
        if inside.sum() >= 16:
            centres.append(float(np.median(level[inside])))
            values.append(float(np.quantile(scatter[inside], 0.25)) / quarter)
    if not values:
        return SILENT
    c1, c0 = np.polyfit(centres, values, 1) if len(centres) >= 2 else (0.0, values[0])
    if c1 < 0:  # noise does not fall with the level: a constant
        c1, c0 = 0.0, float(np.median(values))
    return NoiseModel(max(float(c0), 0.0), float(c1))


def level_and_scatter(y: np.ndarray, x: np.ndarray, response: np.ndarray, where: np.ndarray, *, threads: int = 1):
    """What :func:`fit` takes, from readings ``y`` ``(F, H, W)`` and the scene ``x`` predicted for
    them: at the photosites ``where``, the mean of ``x`` over the frames, and the variance (n - 1
    degrees of freedom) of the readings about ``response`` times it (a strip of rows at a time, on
    ``threads`` threads)."""

    def work(rows):
        inside = where[rows]
        xs = x[:, rows][:, inside]
        return xs.mean(axis=0), (y[:, rows][:, inside] - response[rows][inside][None] * xs).var(axis=0, ddof=1)

    level, scatter = zip(*each_strip(work, y.shape, threads=threads))
    return np.concatenate(level), np.concatenate(scatter)
