"""Overlapping tiles of a plane, solved independently and blended: the layout the accurate and
the scene solvers share.

The tiling depends only on the plane's shape, the core side and the halo, so a result does not
depend on how many workers solved the tiles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EstimationError
from ..geometry.warps import STILL_PX, as_warp, trajectory_rms
from ..parallel import map_ordered
from .result import out_of_range, regauge


def windows(shape: tuple[int, int], core: int, halo: int) -> list[tuple[int, int, int, int]]:
    """``(y0, x0, y1, x1)`` of every tile: a ``core`` px square (cut at the edges) grown by ``halo``."""
    h, w = shape
    return [(max(0, cy - halo), max(0, cx - halo), min(h, cy + core + halo), min(w, cx + core + halo))
            for cy in range(0, h, core) for cx in range(0, w, core)]


@dataclass(frozen=True)
class Tile:
    """One tile's problem, as a worker solves it: its origin in the plane, every frame's crop and
    the crop of the pixels left out (None: none) over the tile and its halo, the motion, the level
    at which the frames clip, the solver's options, each frame's exposure relative to the reference
    (None: all alike) and, for the accurate solver, the frame pairs it compares."""

    y0: int
    x0: int
    frames: np.ndarray  # (F, h, w)
    excluded: np.ndarray | None  # (F, h, w) bool
    motion: object  # maps computed in the worker: a field model's cost a moment each
    saturation: float
    options: object
    exposures: tuple | None = None
    pairs: tuple = ()  # ((s, t), ...)

    def readings(self) -> tuple[np.ndarray, np.ndarray]:
        """The frames in float64 divided by an exact power of two (to about 1: far from float32's
        limits in the products with k; k does not depend on it) and by their exposures, and where
        they are usable: above black, below the clipping level (both on the counts as read) and
        not left out."""
        frames = self.frames.astype(np.float64)
        unit = power_of_two_scale(frames)
        good = usable(frames, self.saturation, self.excluded)
        frames /= unit
        if self.exposures is not None:
            frames /= np.asarray(self.exposures)[:, None, None]
        return frames, good


def usable(frames: np.ndarray, saturation: float | None, excluded: np.ndarray | None) -> np.ndarray:
    """Where readings can be used: above black, below the clipping level (None: nothing clips), not
    left out (``excluded``, None: none)."""
    good = (frames > 0) & (frames < (np.inf if saturation is None else saturation))
    if excluded is not None:
        good &= ~excluded
    return good


def tiles_of(frames: np.ndarray, excluded: np.ndarray | None, motion, saturation: float | None, options,
          exposures=None, pairs: tuple = ()) -> list[Tile]:
    """The :class:`Tile` of every window (:func:`windows`, ``options.tile`` and ``options.halo``), the
    stacks' crops views; ``saturation`` None: nothing clips."""
    saturation = np.inf if saturation is None else float(saturation)
    out = []
    for y0, x0, y1, x1 in windows(frames.shape[1:], options.tile, options.halo):
        crop = (slice(None), slice(y0, y1), slice(x0, x1))
        out.append(Tile(y0, x0, frames[crop], None if excluded is None else excluded[crop], motion, saturation,
                        options, exposures, pairs))
    return out


def power_of_two_scale(frames: np.ndarray) -> float:
    """The power of two nearest the median of the positive samples (1 if none): dividing by
    it is exact, so no sample crosses the saturation level or black."""
    positive = frames[frames > 0]
    median = float(np.median(positive)) if positive.size else 1.0
    return float(2.0 ** np.round(np.log2(median))) if np.isfinite(median) and median > 0 else 1.0


def ramp(shape: tuple[int, int], origin: tuple[int, int], full: tuple[int, int], halo: int) -> np.ndarray:
    """Blend weight of a tile of ``shape`` at ``origin``: 1 in its core, falling linearly to ~0
    across its halo (not at the plane's edges)."""

    def axis(start, length, size):
        pos = np.arange(start, start + length)
        lo = pos - start + 0.5 if start > 0 else np.full(length, np.inf)
        hi = start + length - pos - 0.5 if start + length < size else np.full(length, np.inf)
        return np.clip(np.minimum(lo, hi) / max(halo, 1), 1e-3, 1.0)

    return np.outer(axis(origin[0], shape[0], full[0]), axis(origin[1], shape[1], full[1]))


@dataclass(frozen=True)
class Blended:
    """The tiles' k and confidence as one gauged plane, and what blending counted."""

    k: np.ndarray
    confidence: np.ndarray
    iterations: tuple[int, ...]
    unestimated_pixels: int
    out_of_range_pixels: int
    median_confidence: float


def blend(origins, results, shape: tuple[int, int], *, halo: int, gain_range: tuple[float, float]) -> Blended:
    """Blend each tile's ``(k, confidence, iterations)`` at its ``(y0, x0)`` (``results`` freed as
    they are), leave gains outside ``gain_range`` unestimated and apply the gauge."""
    h, w = shape
    iterations = [r[2] for r in results]
    # where each tile estimated; float32 plane-sized sums (a 12 MP frame: 48 MB each)
    (k_sum, conf_sum), weight_sum = ramp_sums(origins, results, lambda r: (r[0], r[1]), lambda r: r[1] > 0,
                                              (h, w), halo)
    estimated = weight_sum > 0
    k = np.divide(k_sum, weight_sum, out=np.ones((h, w), np.float32), where=estimated)
    confidence = np.divide(conf_sum, weight_sum, out=np.zeros((h, w), np.float32), where=estimated)
    del k_sum, conf_sum, weight_sum
    absurd = out_of_range(k, estimated, gain_range)
    estimated &= ~absurd
    confidence[absurd] = 0.0
    if not estimated.any():
        raise EstimationError("no pixel could be compared between frames (all clipped, dark or out of view)")
    k[~estimated] = 1.0
    regauge(k, estimated)
    k[~estimated] = 1.0
    return Blended(k.astype(np.float32), confidence.astype(np.float32), tuple(iterations),
                   int((~estimated).sum()), int(absurd.sum()), float(np.median(confidence[estimated])))


def ramp_sums(origins, results, arrays, where, shape: tuple[int, ...], halo: int):
    """The sums over tiles of ``arrays(result)`` (each ``shape``'s last two axes cropped to the tile),
    weighted by the tile's :func:`ramp` where ``where(result)``, and the sum of those weights, all
    float32 ``shape``; each tile's ``(y0, x0)`` in ``origins``, ``results`` freed as they are added."""
    sums = None
    weight_sum = np.zeros(shape, np.float32)
    for i, (y0, x0) in enumerate(origins):
        result = results[i]
        results[i] = None
        pieces = arrays(result)
        if sums is None:
            sums = [np.zeros(shape, np.float32) for _ in pieces]
        th, tw = pieces[0].shape[-2:]
        weight = (ramp((th, tw), (y0, x0), shape[-2:], halo) * where(result)).astype(np.float32)
        sl = (..., slice(y0, y0 + th), slice(x0, x0 + tw))
        for total, piece in zip(sums, pieces):
            total[sl] += weight * piece
        weight_sum[sl] += weight
    return sums, weight_sum


def checked_problem(frames, motion, excluded, exposures):
    """A tiled solver's inputs checked: ``frames`` as float32 ``(F, H, W)``, ``motion`` as a warp
    of F frames, ``exposures`` as F positive floats (or None); ``excluded`` must match the frames."""
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must have shape (F, H, W) with F >= 2, got {frames.shape}")
    if excluded is not None and np.shape(excluded) != frames.shape:
        raise ValueError(f"excluded must have the frames' shape {frames.shape}, got {np.shape(excluded)}")
    motion = as_warp(motion)
    if motion.n_frames != frames.shape[0]:
        raise ValueError(f"motion is given for {motion.n_frames} frames, there are {frames.shape[0]}")
    if exposures is not None:
        exposures = tuple(float(c) for c in np.ravel(exposures))
        if len(exposures) != frames.shape[0] or not all(np.isfinite(c) and c > 0 for c in exposures):
            raise ValueError(f"exposures must be {frames.shape[0]} positive numbers, got {exposures}")
    check_motion(motion.homographies, frames.shape[1:])
    return frames, motion, exposures


def check_motion(homographies: np.ndarray, shape: tuple[int, int]) -> None:
    moved = [trajectory_rms(H, np.eye(3), shape, step=8) for H in homographies]
    if max(moved) < STILL_PX:
        raise EstimationError(
            f"no motion: every frame is within {STILL_PX} px of the reference, so the gain cannot be "
            "estimated (pan or shake the camera during the burst)"
        )


def solve_tiles(prepared: list[list], solve_tile, assemble, *, workers: int, progress=None, executor=None) -> list:
    """``assemble(tiles, results)`` of each problem's ``tiles`` in ``prepared``, every tile solved by
    ``solve_tile`` in one go (:func:`parallel.map_ordered`): problems of one tile each still run on
    every worker, and the results are those of one call per problem."""
    results = map_ordered(solve_tile, [t for tiles in prepared for t in tiles], workers=workers, progress=progress,
                          executor=executor)
    solved, start = [], 0
    for tiles in prepared:
        solved.append(assemble(tiles, results[start:start + len(tiles)]))
        start += len(tiles)
    return solved


def each_or_none(many, problems: list, **kwargs) -> list:
    """``many(problems, **kwargs)`` (a ``solve_*_many``), or where that fails (:class:`EstimationError`:
    a problem with no pixel to compare, found after all are solved), each problem alone: None for those
    that fail again. For regions that only measure (a large plane's squares,
    :func:`solving.measured_squares`): one all clipped or black leaves the others' measurement."""
    try:
        return many(problems, **kwargs)
    except EstimationError:
        out = []
        for problem in problems:
            try:
                out.append(many([problem], **kwargs)[0])
            except EstimationError:
                out.append(None)
        return out
