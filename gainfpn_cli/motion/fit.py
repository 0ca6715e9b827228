"""Global warps fitted to tracked point pairs: translation, affine and homography on one robust
inlier set, and the GRIC that compares them."""

from __future__ import annotations

import numpy as np

from ..errors import EstimationError
from ..geometry.warps import apply_homography
from ..metrics import point_noise_variance

#: Parameters of each global model, simplest first.
MODEL_PARAMS = {"translation": 2, "affine": 6, "homography": 8}
MIN_POINTS = {"translation": 3, "affine": 6, "homography": 8}

#: Inlier threshold (px) of the robust homography fit.
INLIER_PX = 0.3
#: Robust fit: USAC_ACCURATE (GC-RANSAC, scored by inlier count), then up to LOCAL_ROUNDS
#: least-squares refits, each keeping the points within LOCAL_SIGMAS x the residual noise (capped at
#: INLIER_PX); against MAGSAC alone: docs/method.md, Measured choices.
LOCAL_ROUNDS = 10
LOCAL_SIGMAS = 2.5

def fit_models(src: np.ndarray, dst: np.ndarray, *, threshold: float = INLIER_PX,
               shape: tuple[int, int] | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Fit translation, affine and homography to point pairs on one robust inlier set.

    The inliers are those of a robust homography (``threshold`` px), refined
    by least-squares refits until stable (see LOCAL_ROUNDS); each model is
    then fitted by least squares on them. Given the frame's ``shape``, the
    points that set leaves are searched for a second one, and whichever
    spans more of the frame (:func:`coverage`) is kept: the dominant motion
    is the one most of the frame follows, not the one with the most points
    (a crisp moving object can hold more corners than a soft background).
    Returns the 3x3 matrices by model and the inlier mask.
    """
    import cv2

    n = len(src)
    if n < MIN_POINTS["homography"]:
        raise EstimationError(f"only {n} points could be tracked; need {MIN_POINTS['homography']}")
    inliers = _robust_inliers(src, dst, threshold)
    if inliers is None:
        raise EstimationError("no homography fits the tracked points")
    rest = np.flatnonzero(~inliers)
    if shape is not None and len(rest) >= MIN_POINTS["homography"]:
        other = _robust_inliers(src[rest], dst[rest], threshold)
        if other is not None and coverage(src[rest[other]], shape) > coverage(src[inliers], shape):
            inliers = np.zeros(n, bool)
            inliers[rest[other]] = True
    if inliers.sum() < MIN_POINTS["homography"]:
        raise EstimationError(f"only {int(inliers.sum())} inliers; need {MIN_POINTS['homography']}")
    s, d = src[inliers], dst[inliers]
    H, _ = cv2.findHomography(s, d, 0)
    A = _fit_affine(s, d)
    T = np.eye(3)
    T[:2, 2] = np.mean(d - s, axis=0)
    return {"translation": T, "affine": A, "homography": H / H[2, 2]}, inliers


def _robust_inliers(src: np.ndarray, dst: np.ndarray, threshold: float) -> np.ndarray | None:
    """Inliers of a robust homography (GC-RANSAC), then of least-squares refits until stable; None if none fits."""
    import cv2

    _, mask = cv2.findHomography(src, dst, cv2.USAC_ACCURATE, threshold, maxIters=5000, confidence=0.9999)
    if mask is None:
        return None
    inliers = mask.ravel().astype(bool)
    for _ in range(LOCAL_ROUNDS):  # local optimisation: refit, re-select at LOCAL_SIGMAS x the noise
        if inliers.sum() < MIN_POINTS["homography"]:
            break
        H, _ = cv2.findHomography(src[inliers], dst[inliers], 0)  # least squares (DLT + Levenberg-Marquardt)
        if H is None:
            break
        residual = transfer_residuals(H, src, dst)
        grown = residual < min(threshold, LOCAL_SIGMAS * np.sqrt(point_noise_variance(residual[inliers])))
        if np.array_equal(grown, inliers):
            break
        inliers = grown
    return inliers


#: :func:`coverage` counts the cells of a COVER_GRID x COVER_GRID grid over the frame.
COVER_GRID = 8


def coverage(points: np.ndarray, shape: tuple[int, int]) -> int:
    """How many cells of a COVER_GRID x COVER_GRID grid over a frame of ``shape`` hold one of the ``(x, y)`` points."""
    h, w = shape
    col = np.clip((np.asarray(points)[:, 0] * COVER_GRID / w).astype(int), 0, COVER_GRID - 1)
    row = np.clip((np.asarray(points)[:, 1] * COVER_GRID / h).astype(int), 0, COVER_GRID - 1)
    return int(np.unique(row * COVER_GRID + col).size)


def _fit_affine(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    design = np.hstack([src, np.ones((len(src), 1))])
    coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
    A = np.eye(3)
    A[:2, :] = coef.T
    return A


def gric(residuals: dict[str, np.ndarray], params: dict[str, float], sigma2: float) -> dict[str, float]:
    """Torr's Geometric Robust Information Criterion of each model on one frame's points.

    ``GRIC = sum_i min(e_i^2 / sigma^2, 4) + p ln(4 n)``: a squared transfer
    error ``e_i`` in units of the tracking noise ``sigma``, capped so that
    outliers -- a moving object -- cost the same under every model, plus
    ``ln(4n)`` per parameter ``p``. All models are scored on all ``n``
    points, so no model is favoured by an inlier set chosen for another
    (2-D maps of 2-D points: the ``d n`` terms are equal and dropped).
    """
    out = {}
    for name, e in residuals.items():
        out[name] = float(np.sum(np.minimum(e**2 / sigma2, 4.0)) + params[name] * np.log(4 * len(e)))
    return out


def transfer_residuals(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distances (px) between ``H src`` and ``dst``."""
    return np.linalg.norm(apply_homography(H, src) - dst, axis=1)
