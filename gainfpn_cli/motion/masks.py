"""What does not follow the global motion: pixels of moving objects, found from dense flow
against the warp and the frames' disagreement."""

from __future__ import annotations

import numpy as np

from ..geometry.warps import as_warp
from ..metrics import MAD_TO_SIGMA
from .track import TRACK_SIGMA, to_uint8

#: A pixel does not follow the global warp when its dense (DIS) flow departs from the warp by more
#: than MASK_FLOW_PX *and* the frames disagree there by more than MASK_SIGMAS robust standard
#: deviations, relative to the brightness (at least MASK_FLOOR x the median); the mask is grown by
#: MASK_GROW_PX. Why both tests, and what they find: docs/method.md, Measured choices.
MASK_FLOW_PX = 1.0
MASK_SIGMAS = 3.5
MASK_FLOOR = 0.25
MASK_GROW_PX = 3
#: Frames larger than this many pixels are compared area-reduced by an
#: integer factor (the flow threshold scales with it). Measured with a 10 %
#: object moving 2 px per frame (worst frame; textured object pixels found /
#: rest flagged): 960x1280 full size 81-91 % / 9-13 %, halved 81-90 % /
#: 6-7 %; 12 MP halved 88 % / 0.3 %, a third 86 % / 0.3 % in half the time
#: (0.27 s per frame), a fifth 76 %.
MASK_PIXELS = 2**21


def mask_factor(shape: tuple[int, int]) -> int:
    """The integer reduction :func:`moving_masks` compares frames of ``shape`` at."""
    return max(1, int(np.ceil(np.sqrt(shape[0] * shape[1] / MASK_PIXELS))))


def reduced_smooth(frames: np.ndarray, factor: int, exposures=None) -> tuple[list, np.ndarray]:
    """Each frame smoothed by TRACK_SIGMA, area-reduced ``factor`` times (one full-size blurred frame
    at a time) and divided by its exposure (none: all alike), and the map from frame pixels to
    reduced pixels."""
    import cv2

    h, w = frames.shape[1:]
    size = (max(1, w // factor), max(1, h // factor))
    sx, sy = size[0] / w, size[1] / h
    # reduced pixel centres: x_r = (x + 0.5) * w_r / w - 0.5
    to_reduced = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])

    def smoothed(frame: np.ndarray) -> np.ndarray:
        blurred = cv2.GaussianBlur(frame, (0, 0), TRACK_SIGMA)
        return blurred if factor == 1 else cv2.resize(blurred, size, interpolation=cv2.INTER_AREA)

    reduced = [smoothed(f) for f in frames]
    if exposures is not None:
        for r, c in zip(reduced, exposures):
            r /= np.float32(c)  # a fresh array: the frames are not touched
    return reduced, to_reduced


def moving_masks(frames: np.ndarray, motion, *, factor: int | None = None, exposures=None) -> np.ndarray:
    """Pixels of each frame (in its own coordinates) that do not follow the estimated motion.

    ``motion`` is a warp of :mod:`geometry.warps` or ``(F, 3, 3)`` homographies.
    Frame t (t >= 1) is compared with the reference: DIS flow from t to the
    reference against the motion's prediction, and the smoothed brightness of
    the two. The reference's own mask is the union of its comparisons with
    every frame. The comparison runs on frames reduced ``factor`` times
    (default :func:`mask_factor`), each divided by its exposure relative to
    the reference (``exposures``; none: all alike). Returns bool ``(F, H, W)``.
    """
    import cv2

    from ..geometry.resample import positions, sample

    frames = np.asarray(frames, np.float32)
    n, h, w = frames.shape
    factor = mask_factor((h, w)) if factor is None else int(factor)
    lo, hi = np.percentile(frames[0], [0.5, 99.5])
    smooth, to_reduced = reduced_smooth(frames, factor, exposures)
    size = smooth[0].shape[::-1]  # (w, h) of the reduced frames
    sx, sy = to_reduced[0, 0], to_reduced[1, 1]
    track = [to_uint8(f, lo, hi) for f in smooth]  # tracking_image without blurring twice
    grid = np.stack(np.meshgrid(np.arange(size[0], dtype=np.float64), np.arange(size[1], dtype=np.float64)), axis=-1)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    limit = MASK_FLOW_PX * min(sx, sy)
    motion = as_warp(motion).conjugate(np.linalg.inv(to_reduced))
    region = (0, 0, size[1], size[0])

    def departs(a: int, b: int) -> np.ndarray:
        """Pixels of frame a whose content is not where the motion says frame b sees it."""
        M = motion.pair(a, b, region)
        flow = dis.calc(track[a], track[b], None)
        where = positions(M, (size[1], size[0]))  # where frame b sees each pixel, by the motion
        diff = np.abs(smooth[a] - sample(smooth[b], M, (size[1], size[0]), kernel="bilinear"))
        diff /= np.maximum(smooth[a], MASK_FLOOR * float(np.median(smooth[a][::2, ::2])))  # relative, as the FPN
        sigma = MAD_TO_SIGMA * float(np.median(diff[::2, ::2]))  # a robust spread: a quarter of the pixels suffice
        # a pixel frame b does not see (outside it, or hidden in it under a layered warp:
        # geometry.warps.NOWHERE) is compared with nothing, so it departs from nothing
        x, y = where[..., 0], where[..., 1]
        seen = (x >= 0) & (x <= size[0] - 1) & (y >= 0) & (y <= size[1] - 1)
        off = flow + grid - where  # the flow's end point against the motion's
        return seen & (off[..., 0] ** 2 + off[..., 1] ** 2 > limit**2) & (diff > MASK_SIGMAS * sigma)

    reduced = np.zeros((n, size[1], size[0]), np.uint8)
    for t in range(1, n):
        reduced[t] = departs(t, 0)
        reduced[0] |= departs(0, t)
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * MASK_GROW_PX + 1,) * 2)
    out = np.empty((n, h, w), bool)
    for t in range(n):
        full = reduced[t] if factor == 1 else cv2.resize(reduced[t], (w, h), interpolation=cv2.INTER_NEAREST)
        out[t] = cv2.dilate(full, grow) > 0
    return out
