"""Per-photosite statistics over a frame stack ``(F, H, W)``, a strip of rows at a time.

The defect search (:mod:`solve.defects`) takes medians, variances and fits along the frames of
every photosite; worked on a strip of rows at a time, each of their temporaries is a strip's,
not a frame stack's (768 MB of float32 at 12 MP x 16 frames).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

#: Readings (frames x photosites) of a strip of rows: each temporary of a strip is then 16 MB of
#: float32, whatever the frame size.
STRIP_READINGS = 2**22


def strips(shape: tuple[int, ...], *, parts: int = 1) -> list[slice]:
    """Slices of rows covering a stack of ``shape`` ``(F, H, W)``, each of at most
    :data:`STRIP_READINGS` / ``parts`` readings, and one row at least."""
    n_frames, h, w = shape
    rows = max(1, STRIP_READINGS // parts // max(n_frames * w, 1))
    return [slice(y0, min(y0 + rows, h)) for y0 in range(0, h, rows)]


def each_strip(work, shape: tuple[int, ...], *, parts: int = 1, threads: int = 1) -> list:
    """``[work(rows) for rows in strips(shape, parts=...)]`` on ``threads`` threads, with strips
    ``threads`` times smaller: as many temporaries alive at once as on one thread. Each call works
    on its own strip (its rows of preallocated outputs, or a result returned in order) and every
    statistic is along the frames, so nothing depends on ``threads``; NumPy's loops over a strip
    release the GIL."""
    pieces = strips(shape, parts=parts * max(threads, 1))
    if threads <= 1 or len(pieces) < 2:
        return [work(rows) for rows in pieces]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(work, pieces))


def nan_median(stack: np.ndarray, *, threads: int = 1) -> np.ndarray:
    """``np.nanmedian(stack, axis=0)`` (NaN where every value is), by one sort along the short
    axis: NumPy's goes through masked arrays for a short axis, 10x slower on a frame stack.
    A strip (:func:`strips`) at a time, so that the sort's copy stays small, on ``threads``
    threads (:func:`each_strip`)."""
    stack = np.asarray(stack)
    if stack.ndim == 3 and stack.size > STRIP_READINGS // max(threads, 1) and stack.shape[1] > 1:
        out = np.empty(stack.shape[1:], stack.dtype)

        def work(rows):
            out[rows] = nan_median(stack[:, rows])

        each_strip(work, stack.shape, threads=threads)
        return out
    ordered = np.sort(stack, axis=0)  # NaN last
    count = np.isfinite(ordered).sum(axis=0)
    lower = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[None], axis=0)[0]
    upper = np.take_along_axis(ordered, (count // 2)[None], axis=0)[0] if len(stack) else lower
    median = (lower + upper) / 2
    median[count == 0] = np.nan
    return median


@dataclass(frozen=True)
class Relative:
    """Frames brought to the reference's exposure, ``read / exposures``, divided a frame (``[t]``)
    or a strip of rows (``[:, rows]``) at a time as they are used: the divided stack would be
    another 768 MB at 12 MP x 16 frames, on top of the read one. It stands in for that stack
    wherever only frames and strips of it are taken."""

    read: np.ndarray  # (F, H, W) float32
    exposures: np.ndarray  # (F,) float32

    @property
    def shape(self) -> tuple[int, ...]:
        return self.read.shape

    def __getitem__(self, key):
        if isinstance(key, (int, np.integer)):
            return self.read[key] / self.exposures[key]
        if not (isinstance(key, tuple) and key[0] == slice(None)):
            raise IndexError("a frame [t] or every frame's rows [:, rows]")
        return self.read[key] / self.exposures[:, None, None]
