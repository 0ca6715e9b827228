"""Hot photosites of a CFA colour's plane tested once more, against a latent scene fitted without them.

The defect search's two predictions of the scene (:mod:`solve.predict`) come from the plane's
readings of other frames as they lie: on an aliased plane (a colour of a mosaic, a sharp scene)
they miss the edges a hot photosite's trajectory crosses, which is where its offset shows. The
scene model (:mod:`solve.scenemodel`, a latent scene three times finer than the plane, every
frame's readings sampling it) places those edges better, but fitted to a hot photosite's own
readings it takes part of the offset up. So the photosites most likely to be hot, the
:data:`SUSPECTS` share whose response against the sharper prediction is highest, are left out
of one fit, with a control lattice of photosites (every :data:`CONTROL`-th on each axis) whose
scores give a healthy photosite's scale, and each suspect's offset fitted with the gain
(:func:`along.offset_scores`) against the scene rendered where it is is tested: hot past
:data:`Z_LEFT_OUT` robust spreads of the control's (docs/limits.md, "Defective photosites").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..parallel import imap_ordered
from .along import MIN_FIT_FRAMES, centre_and_spread, offset_scores, responses
from .scene import SceneOptions
from .scenemodel import fit_tile
from .tiling import Tile, power_of_two_scale, ramp, windows

#: Share of a plane's photosites left out of the fit as suspects: those whose response against the
#: sharper prediction is highest. On 240x320 raw12 RGGB dead-leaves bursts at 75 % exposure with
#: 0.5 % defects (seeds 0-1 and 2-3; z 20-40 / over 40 of docs/limits.md's hotz table): 2 % found
#: 88 / 96 % and 92 / 96 %, 5 % 87 / 95 % and 90 / 97 %, 10 % 88 / 93 % and 90 / 97 %.
SUSPECTS = 0.05
#: Period of the control lattice (photosites (i, j) with i % CONTROL == 1 and j % CONTROL == 2).
CONTROL = 4
#: Offset score (in the control photosites' robust spread) past which a suspect is hot. On the same
#: bursts (and the healthy photosites flagged by the whole search on the four without defects): 6:
#: 89 / 97 % and 92 / 97 % (6), 7: 87 / 95 % and 90 / 97 % (5), 8: 86 / 94 % and 87 / 95 % (3, as
#: without the test).
Z_LEFT_OUT = 7.0
#: Readings of a suspect from which Z_LEFT_OUT applies as it is (8 frames); with fewer, the fit's own
#: scatter over fewer degrees of freedom has heavier tails (:func:`threshold`: 10.8 at 6, 8.3 at 7). Ten
#: defect-free 144x176 raw12 bursts (seeds 20-29), healthy photosites flagged of 253 440 at 6 / 7
#: frames: dead leaves at 75 % with 7 throughout 41 / 18, with these 10 / 15, the search without the
#: test 10 / 12 (7.5 %: 2 / 5 against 2 / 2; procedural 3 / 1 and 3 / 0 against 3 / 1 and 2 / 0).
REFERENCE_READINGS = 8
#: Fewest control photosites fitted for their scores' spread to be measured.
MIN_CONTROL = 16
#: The latent scene's samples per plane pixel on each axis (as docs/bench/hot_ceiling.py's). With 20
#: CG iterations, 2 cost 0.6x of 3, and the bursts of Z_LEFT_OUT found 84 / 91 % and 86 / 96 % against
#: 88 / 95 % and 89 / 97 %.
SCALE = 3
#: Conjugate-gradient iterations of each Gauss-Newton step at most (the scene solver's: 20). At 10 the
#: fit of a 500x750 plane of 8 frames costs 0.64x, and those bursts found 87 / 95 % and 90 / 97 %.
CG_ITERATIONS = 10


def left_out_hot(frames, read, warp, response: np.ndarray, *, tested: np.ndarray, noise, floor: float,
                 aperture: float, good, exposures=None, threads: int = 1) -> np.ndarray:
    """The suspects of one plane that the latent scene fitted without them shows hot, ``(H, W)``
    bool. ``frames`` are the readings as the search tests them (divided by their exposures),
    ``read`` as read (``(F, H, W)``), ``exposures`` ``(F,)`` relative to the reference's (None: all
    alike), ``warp`` maps between their grids; ``response`` is the sharper prediction's, where
    ``tested``; ``noise`` the search's noise model, ``floor`` its lowest level for a ratio,
    ``aperture`` the photosites' width in plane pixels (0.5 on a CFA colour's plane), ``good(t,
    frame)`` frame ``t``'s usable readings. Offsets are fitted where at least
    :data:`along.MIN_FIT_FRAMES` readings are usable; the latent scene's tiles are fitted on
    ``threads`` worker processes and the statistics along the frames run a strip of rows at a time on
    as many threads (the same result on any number)."""
    n_frames, h, w = read.shape
    if not tested.any():
        return np.zeros((h, w), bool)
    suspects = tested & (response >= np.quantile(response[tested], 1 - SUSPECTS))
    rows, cols = np.ogrid[:h, :w]
    control = (rows % CONTROL == 1) & (cols % CONTROL == 2) & ~suspects
    out = suspects | control
    x, usable = _rendered(frames, read, warp, out, good, aperture, exposures, threads)
    usable &= x > floor
    ratio, scatter, count, *_ = responses(frames, x, usable, threads)
    fitted = count >= MIN_FIT_FRAMES  # (offset_scores scores only those: 0 elsewhere)
    healthy = control & fitted
    if np.count_nonzero(healthy) < MIN_CONTROL:  # too few to tell a healthy photosite's scale
        return np.zeros((h, w), bool)
    typical, spread = centre_and_spread(ratio[healthy])
    offsets = offset_scores(frames, x, usable, typical, spread, scatter, noise, threads)
    centre, scale = centre_and_spread(offsets[healthy])
    shown = offsets - centre > threshold(count) * max(scale, 1e-12)
    return suspects & fitted & shown


def threshold(count: np.ndarray) -> np.ndarray:
    """The score past which a suspect fitted on ``count`` readings (non-negative integers) is hot:
    :data:`Z_LEFT_OUT` from :data:`REFERENCE_READINGS` on, above it under that, where the fit's own
    scatter, measured on ``count - 2`` degrees of freedom, gives Student's heavier tails (the same
    tail probability)."""
    from scipy import stats

    tail = stats.t.sf(Z_LEFT_OUT, REFERENCE_READINGS - 2)
    count = np.asarray(count, np.intp)  # (readings: a few values, SciPy's quantile once for each)
    dof = np.maximum(np.arange(count.max(initial=0) + 1) - 2.0, 1)
    return np.maximum(Z_LEFT_OUT, stats.t.isf(tail, dof))[count]


def _rendered(frames, read, warp, out: np.ndarray, good, aperture: float, exposures, workers: int = 1):
    """The latent scene fitted without the photosites ``out`` (nor the readings ``good`` refuses),
    rendered at every photosite in every frame (divided by the exposures; 0 where a photosite does
    not see it), and where a reading is usable (``(F, H, W)`` float32 and bool); tiles of the scene
    solver's size, fitted on ``workers`` local processes (:func:`parallel.imap_ordered`: each tile made
    as a worker takes it, its rendering added in as it comes) and blended across their halos where
    each sees the reading (near a seam a reading of a shaken frame can fall outside one tile's scene:
    that tile's rendering is 0 there, not a value)."""
    n_frames, h, w = read.shape
    options = SceneOptions(scale=SCALE, aperture=aperture, refine_frames=False, cg_iterations=CG_ITERATIONS)
    usable = np.stack([good(t, frames[t]) for t in range(n_frames)])
    exposures = None if exposures is None else tuple(float(e) for e in exposures)
    boxes = windows((h, w), options.tile, options.halo)
    tiles = _Crops(boxes, lambda y0, x0, y1, x1: Tile(
        y0, x0, np.ascontiguousarray(read[:, y0:y1, x0:x1], np.float32),
        ~usable[:, y0:y1, x0:x1] | out[None, y0:y1, x0:x1], warp, np.inf, options, exposures))
    total = np.zeros(read.shape, np.float32)
    weight = np.zeros(read.shape, np.float32)
    for (y0, x0, y1, x1), fitted in zip(boxes, imap_ordered(_render_tile, tiles, workers=workers)):
        if fitted is None:
            continue
        rendering, sees = fitted
        crop = (slice(None), slice(y0, y1), slice(x0, x1))
        ramped = ramp((y1 - y0, x1 - x0), (y0, x0), (h, w), options.halo).astype(np.float32) * sees
        total[crop] += ramped * rendering
        weight[crop] += ramped
    np.divide(total, weight, out=total, where=weight > 0)  # (0 where no tile sees the reading)
    return total, usable


def _render_tile(tile: Tile) -> tuple[np.ndarray, np.ndarray] | None:
    """One tile's latent scene fitted and rendered at its readings (in the frames' units), and which
    readings it sees (``(F, h, w)`` float32 and bool); None if it could not be fitted."""
    fit = fit_tile(tile)
    if fit is None:
        return None
    shape = tile.frames.shape
    sees = (np.asarray(fit.A.wv) != 0).any(axis=1).reshape(shape)  # (rows out of view: zero weights)
    unit = np.float32(power_of_two_scale(tile.frames.astype(np.float64)))  # the tile's readings' unit (Tile.readings)
    return np.asarray(fit.predicted, np.float32).reshape(shape) * unit, sees


class _Crops(Sequence):
    """``crop(*box)`` of each of ``boxes``, made as it is asked for: a plane's tiles (their halos
    twice over) are not all held at once (the pool takes a task as a worker is ready for it)."""

    def __init__(self, boxes, crop):
        self.boxes, self.crop = boxes, crop

    def __len__(self):
        return len(self.boxes)

    def __getitem__(self, i):
        return self.crop(*self.boxes[i])
