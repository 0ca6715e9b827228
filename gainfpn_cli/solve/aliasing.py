"""How aliased a burst is: what interpolation fails to predict between frames, against the noise.

Frame 0 is predicted from frame ``t`` by cubic interpolation at the positions the motion gives.
The prediction error holds the two readings' temporal noise and gain FPN, and the scene detail
that interpolation cannot reconstruct (the aliased part). At a whole-pixel shift interpolation
copies a reading, so only noise and FPN remain; at a half-pixel shift it must reconstruct the
scene between samples. Dividing each squared error by ``1 + sum(w^2)`` (``w``: the kernel's
weights at that position) makes the noise and white FPN part the same at every sub-pixel
position, so what grows with the distance from a whole-pixel shift is the aliased part.

The excess is fitted per pixel across the frames (each pixel of frame 0 sees a different
sub-pixel position in each frame; a per-pixel mean takes out the scene content and the noise
level, which do not change with the frame): the slope of the normalised squared error against
``sin^2(pi fx) + sin^2(pi fy)`` (``f``: the position's sub-pixel part), times that quantity's
mean, over the mean normalised error that remains. 0: interpolation predicts the burst to its
noise; 0.25: a quarter more error than the noise, all of it aliasing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.resample import bounded, positions, sample, valid_samples
from ..geometry.warps import NOWHERE

#: OpenCV's cubic convolution kernel parameter (``INTER_CUBIC``: Keys' kernel with a = -0.75).
CUBIC_A = -0.75
#: Fewest frames a pixel needs valid predictions from to enter the fit (its mean over frames
#: takes out its scene content and noise level).
MIN_FRAMES = 3
#: Fewest such pixels for a measurement; with fewer, the excess is not measured (None).
MIN_PIXELS = 1000


@dataclass(frozen=True)
class Aliasing:
    """The aliased part of the pairwise prediction error over its noise and FPN part (None if not
    measurable: too few pixels seen by enough frames), and the pixels it was measured on."""

    excess: float | None
    pixels: int


def cubic_weights(phase: np.ndarray) -> list[np.ndarray]:
    """The 4 weights of Keys' cubic kernel (a = :data:`CUBIC_A`) at sub-pixel ``phase`` in [0, 1),
    for the samples at offsets -1, 0, 1, 2."""
    out = []
    for offset in (-1, 0, 1, 2):
        x = np.abs(phase - offset)
        near = (CUBIC_A + 2) * x**3 - (CUBIC_A + 3) * x**2 + 1
        far = CUBIC_A * (x**3 - 5 * x**2 + 8 * x - 4)
        out.append(np.where(x <= 1, near, np.where(x < 2, far, 0.0)))
    return out


def noise_gain(phase_xy: np.ndarray) -> np.ndarray:
    """``sum(w^2)`` of the 2-D cubic kernel at sub-pixel positions ``(..., 2)``: the variance an
    interpolated sample keeps of white noise (1 at a whole-pixel shift, 0.52 at half a pixel)."""
    gains = [sum(w**2 for w in cubic_weights(phase_xy[..., axis])) for axis in (0, 1)]
    return gains[0] * gains[1]


def aliasing(frames: np.ndarray, motion, *, exposures=None, good: np.ndarray | None = None,
             region: tuple[slice, slice] | None = None) -> Aliasing:
    """The aliasing excess (module docstring) of frame 0 of ``frames`` (``(T, H, W)``, one plane)
    against frames ``1..T-1``, on ``region`` of frame 0 (rows, columns; the whole frame if None).

    ``motion`` maps frame 0's pixels to every frame's (``pair``, as :mod:`geometry.warps`);
    ``exposures`` (``T``) are each frame's relative to frame 0's; ``good`` ``(T, H, W)`` marks the
    readings that may be used (not clipped, not moving)."""
    frames = np.asarray(frames, np.float32)
    T, h, w = frames.shape
    rows, columns = region if region is not None else (slice(0, h), slice(0, w))
    y0, x0 = rows.start or 0, columns.start or 0
    shape = (len(range(h)[rows]), len(range(w)[columns]))
    box = (y0, x0) + shape
    reference = frames[0][rows, columns]
    ok0 = np.ones(shape, bool) if good is None else good[0][rows, columns]
    q = np.zeros((T - 1,) + shape)
    b = np.zeros_like(q)
    valid = np.zeros(q.shape, bool)
    for t in range(1, T):
        M = bounded(_in_frame(motion.pair(0, t, box), y0, x0), (h, w))
        xy = positions(M, shape)
        scale = 1.0 if exposures is None else float(exposures[0]) / float(exposures[t])
        predicted = scale * sample(frames[t], M, shape, kernel="cubic")
        source_ok = np.ones((h, w), bool) if good is None else good[t]
        valid[t - 1] = ok0 & valid_samples(source_ok, M, shape, kernel="cubic")
        phase = xy - np.floor(xy)
        # squared in float64: float32 squares overflow at scales past 1e19 (tests/test_extremes.py)
        q[t - 1] = np.square(reference - predicted, dtype=np.float64) / (1.0 + noise_gain(phase))
        b[t - 1] = (np.sin(np.pi * phase) ** 2).sum(axis=-1)
    seen = valid.sum(axis=0)
    use = valid & (seen >= MIN_FRAMES)[None]
    pixels = int(np.sum(seen >= MIN_FRAMES))
    if pixels < MIN_PIXELS:
        return Aliasing(None, pixels)
    count = np.maximum(use.sum(axis=0), 1)
    q_dev = np.where(use, q - np.where(use, q, 0).sum(axis=0) / count, 0.0)
    b_dev = np.where(use, b - np.where(use, b, 0).sum(axis=0) / count, 0.0)
    spread = float(np.sum(b_dev**2))
    if spread <= 0:  # every frame at the same sub-pixel position: nothing to compare
        return Aliasing(None, pixels)
    slope = float(np.sum(q_dev * b_dev)) / spread
    aliased = slope * float(b[use].mean())
    rest = float(q[use].mean()) - aliased
    return Aliasing(aliased / rest if rest > 0 else None, pixels)


def _in_frame(M: np.ndarray, y0: int, x0: int) -> np.ndarray:
    """A map from a region's pixels (at ``y0, x0``) to another region's, as one to frame pixels
    (``pair`` gives region coordinates at both ends)."""
    if M.shape == (3, 3):
        return np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]]) @ M
    M = np.array(M, np.float32)
    somewhere = M[..., 0] != NOWHERE  # a layered warp's points seen by no layer stay marked
    M[somewhere] += np.array([x0, y0], np.float32)
    return M
