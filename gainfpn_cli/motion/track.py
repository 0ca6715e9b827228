"""Tracking: corners in the reference followed into each frame (pyramidal Lucas-Kanade),
seeded by a coarse phase-correlation shift.

Points are ``(x, y)`` in the frame's pixel coordinates (docs/method.md, Conventions).
"""

from __future__ import annotations

import numpy as np

from ..errors import EstimationError

#: Gaussian sigma (px) applied before tracking: gain FPN is white at the pixel
#: scale, scene structure is not, so smoothing suppresses the static pattern
#: that otherwise pulls corners toward zero motion. Measured on 240x320
#: bursts with 5 % FPN, worst-frame RMS error: 1.31 px unsmoothed, 0.24 px at
#: sigma 1.5, 0.048 px at sigma 1.5 with TRACK_QUALITY 0.03.
TRACK_SIGMA = 1.5
#: goodFeaturesToTrack quality: keep corners at least this fraction as
#: strong as the best (weak "corners" in flat areas are FPN, not scene).
TRACK_QUALITY = 0.03
#: Corners are detected in GRID x GRID cells, each with its own quality
#: threshold, so that a strongly textured object cannot take every corner
#: from a softer background.
GRID = 4

def to_uint8(frame: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Scale ``[lo, hi]`` to 0..255, rounded and saturated (OpenCV's trackers take 8-bit images only)."""
    import cv2

    frame = np.asarray(frame, np.float32)
    span = float(hi) - float(lo)
    alpha = 255.0 / span if span > 0 else 0.0  # relative: frames of any scale (1e-33 or 1e38) track alike
    return cv2.addWeighted(frame, alpha, frame, 0.0, -float(lo) * alpha, dtype=cv2.CV_8U)  # one pass


def tracking_image(frame: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The 8-bit, FPN-suppressed image that points are tracked on."""
    import cv2

    return to_uint8(cv2.GaussianBlur(np.asarray(frame, np.float32), (0, 0), TRACK_SIGMA), lo, hi)


def find_corners(reference: np.ndarray, *, max_points: int = 4000, quality: float = TRACK_QUALITY,
                 ignore: np.ndarray | None = None) -> np.ndarray:
    """Shi-Tomasi corners of the uint8 reference, cell by cell: ``(n, 1, 2)`` float32 ``(x, y)``.

    None is taken where the bool ``ignore`` is set (a moving object's pixels:
    its strong corners would otherwise crowd out the background's).

    Each cell is searched in its own crop (not through a mask of the whole
    frame, which costs a corner-strength map of the whole frame per cell).
    """
    import cv2

    h, w = reference.shape
    spacing = max(4, int(np.sqrt(h * w / max_points)))
    pad = 8  # > blockSize // 2 + Sobel radius: strengths in the cell are those of the whole frame
    cells = []
    for y0 in np.linspace(0, h, GRID + 1).astype(int)[:-1]:
        for x0 in np.linspace(0, w, GRID + 1).astype(int)[:-1]:
            y1, x1 = min(h, y0 + -(-h // GRID)), min(w, x0 + -(-w // GRID))
            cy, cx = max(0, y0 - pad), max(0, x0 - pad)
            crop = reference[cy : min(h, y1 + pad), cx : min(w, x1 + pad)]
            mask = np.zeros(crop.shape, np.uint8)
            mask[y0 - cy : y1 - cy, x0 - cx : x1 - cx] = 1
            if ignore is not None:
                mask[ignore[cy : cy + crop.shape[0], cx : cx + crop.shape[1]]] = 0
            found = cv2.goodFeaturesToTrack(crop, maxCorners=max(1, max_points // GRID**2), qualityLevel=quality,
                                            minDistance=spacing, blockSize=7, mask=mask)
            if found is not None:
                cells.append(found + np.array([cx, cy], np.float32))
    return np.concatenate(cells).astype(np.float32) if cells else np.empty((0, 1, 2), np.float32)


def track_points(reference: np.ndarray, frame: np.ndarray, corners: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the reference (:func:`find_corners` unless given) tracked into ``frame`` by pyramidal Lucas-Kanade.

    Both images are uint8. Points whose forward-backward track misses its
    start by more than 0.1 px are dropped. Returns ``(src, dst)``, each
    ``(n, 2)`` float64 ``(x, y)``.
    """
    corners = find_corners(reference) if corners is None else corners
    moved, ok = track_corners(reference, frame, corners)
    return corners.reshape(-1, 2)[ok].astype(np.float64), moved[ok]


def track_corners(reference: np.ndarray, frame: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`track_points` keeping every corner: ``(moved (n, 2) float64, tracked (n,) bool)``."""
    import cv2

    if len(corners) == 0:
        return np.empty((0, 2)), np.empty(0, bool)
    params = dict(winSize=(21, 21), maxLevel=5, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-3))
    shift = coarse_shift(reference, frame)
    try:
        guess = (corners + shift.astype(np.float32)).astype(np.float32)
        moved, st1, _ = cv2.calcOpticalFlowPyrLK(reference, frame, corners, guess, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                 **params)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(frame, reference, moved, corners.copy(),
                                                flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params)
    except cv2.error as exc:
        raise EstimationError(f"point tracking failed: {exc.err}") from None
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm((back - corners).reshape(-1, 2), axis=1) < 0.1)
    return moved.reshape(-1, 2).astype(np.float64), ok


#: Phase correlation runs on the frames area-reduced to at most this many
#: pixels: its shift only seeds the tracker's pyramid.
COARSE_PIXELS = 2**19


def coarse_shift(reference: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """The dominant translation ``(dx, dy)`` of ``frame`` against ``reference`` (phase correlation).

    It seeds the point tracker, so that a large pan or a strongly textured
    moving object cannot lead the pyramid astray; it needs no features and
    is robust to a minority of the frame moving on its own.
    """
    import cv2

    h, w = reference.shape
    factor = max(1, int(np.ceil(np.sqrt(h * w / COARSE_PIXELS))))
    size = (max(1, w // factor), max(1, h // factor))
    a, b = (cv2.resize(img.astype(np.float32), size, interpolation=cv2.INTER_AREA) for img in (reference, frame))
    window = cv2.createHanningWindow(size, cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(a, b, window)
    shift = np.array([dx, dy]) * np.array([w / size[0], h / size[1]])
    return shift if np.all(np.isfinite(shift)) else np.zeros(2)
