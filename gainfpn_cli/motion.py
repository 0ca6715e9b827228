"""Motion: where each reference pixel is seen in every other frame.

Conventions (METHOD.md section 6): arrays are ``(row, col)``; points are
``(x, y)``; ``H_t_ref`` maps reference pixel coordinates to frame ``t``;
``flow_xy[..., 0] = dx``, ``flow_xy[..., 1] = dy``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import EstimationError, TrackingError
from .fieldfit import FIELD_CELLS, fit_field
from .fieldfit import residuals as field_residuals
from .layers import find_layers, label_pixels
from .trajectory import FieldWarp, GlobalWarp, LayeredWarp, apply_homography, as_warp


def positions_from_homography(H: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Position in frame t of every reference pixel, for ``H = H_t_ref``.

    Returns
    -------
    ndarray of float64, shape (H, W, 2)
        ``[..., 0]`` = x, ``[..., 1]`` = y in frame t's pixel coordinates.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"H must be a finite 3x3 matrix, got shape {H.shape}")
    h, w = shape
    ys, xs = np.arange(h, dtype=np.float64)[:, None], np.arange(w, dtype=np.float64)[None, :]  # broadcast, no grids
    den = (H[2, 0] * xs + H[2, 2]) + H[2, 1] * ys
    out = np.empty((h, w, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide((H[0, 0] * xs + H[0, 2]) + H[0, 1] * ys, den, out=out[..., 0])
        np.divide((H[1, 0] * xs + H[1, 2]) + H[1, 1] * ys, den, out=out[..., 1])
    out[~np.isfinite(out)] = np.nan  # points sent to infinity have no position
    return out


def positions_from_flow(flow_xy: np.ndarray) -> np.ndarray:
    """Position in the moving frame of every reference pixel: ``p + flow``."""
    flow_xy = np.asarray(flow_xy, dtype=np.float64)
    if flow_xy.ndim != 3 or flow_xy.shape[2] != 2:
        raise ValueError(f"flow_xy must have shape (H, W, 2), got {flow_xy.shape}")
    h, w = flow_xy.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([xs + flow_xy[..., 0], ys + flow_xy[..., 1]], axis=-1)


# ---------------------------------------------------------------------------
# global warps from the frames

#: Parameters of each global model, simplest first.
MODEL_PARAMS = {"translation": 2, "affine": 6, "homography": 8}
MIN_POINTS = {"translation": 3, "affine": 6, "homography": 8}
#: Every model fitted frame by frame, simplest first: the global ones, then the fields of :mod:`fieldfit`.
MODELS = [*MODEL_PARAMS, *FIELD_CELLS]
#: Every model: those, and scene layers (:mod:`layers`), fitted to the whole burst at once.
ALL_MODELS = [*MODELS, "layers"]


@dataclass(frozen=True)
class MotionResult:
    """The motion of every frame relative to the reference.

    Attributes
    ----------
    homographies : ndarray of float64, shape (F, 3, 3)
        ``H_t_ref`` under the chosen model (identity for the reference); for
        a field model, its homography part.
    model : str
        The chosen model (a key of MODELS).
    per_frame : list of dict
        For each frame: ``tracked`` and ``inliers`` point counts, ``rms_px``
        (residual under the chosen model on the points it keeps) and
        ``gric`` of each model.
    reason : str
        Why that model was chosen.
    warp : GlobalWarp, FieldWarp or LayeredWarp
        The motion as maps between frames.
    layers : list of dict
        For the layers model: each secondary layer's model and point count.
    """

    homographies: np.ndarray
    model: str
    per_frame: list = field(default_factory=list)
    reason: str = ""
    warp: GlobalWarp | FieldWarp | LayeredWarp | None = None
    layers: list = field(default_factory=list)


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
#: Inlier threshold (px) of the robust homography fit.
INLIER_PX = 0.3
#: Robust fit: USAC_ACCURATE (GC-RANSAC, scored by inlier count), then up
#: to LOCAL_ROUNDS least-squares refits, each keeping the points within
#: LOCAL_SIGMAS x the residual noise (capped at INLIER_PX). Measured on 36
#: held-out 200x260 bursts (seeds 5-10, shake / 4 px shake / 25 px drift,
#: with and without a 10 % moving object), worst frame per burst:
#: MAGSAC alone median 0.053 / 0.088 px (object), one burst off by 28 px
#: (MAGSAC preferred the crisp object's 48 points to 96 background ones);
#: this scheme median 0.042 / 0.051 px, worst 0.085 / 0.125 px.
LOCAL_ROUNDS = 10
LOCAL_SIGMAS = 2.5
#: An estimated displacement below this (px, RMS over the frame) cannot be
#: told from zero: it is the accuracy the motion estimate is held to.
STILL_PX = 0.05


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
        grown = residual < min(threshold, LOCAL_SIGMAS * np.sqrt(_noise_variance(residual[inliers])))
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


def _noise_variance(distances: np.ndarray) -> float:
    """Per-coordinate variance of 2-D Gaussian errors from their lengths: median(d^2) = 2 ln 2 sigma^2."""
    return float(np.median(distances**2)) / (2 * np.log(2))


def transfer_residuals(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distances (px) between ``H src`` and ``dst``."""
    return np.linalg.norm(apply_homography(H, src) - dst, axis=1)


def estimate_motion(
    frames: np.ndarray,
    *,
    model: str = "auto",
    ignore: np.ndarray | None = None,
    exposures=None,
    progress=None,
) -> MotionResult:
    """The motion of every frame of a burst whose first frame is the reference.

    Corners of the reference are tracked into each frame (pyramidal
    Lucas-Kanade: shakes of tens of pixels work); the global models and the
    field models (:mod:`fieldfit`) are fitted to them, and scene layers
    (:mod:`layers`) split off the points the best global model leaves; where
    there are any, every frame's models are fitted again without their
    points, whatever the model. With ``model="auto"`` the burst gets the model with the lowest :func:`gric`
    summed over frames -- the simplest the data support. No corner is taken
    where the bool ``(H, W)`` mask ``ignore`` is set (pixels known to move).
    Frame ``t`` is compared at the reference's brightness: divided by
    ``exposures[t]``, its exposure relative to the reference (:mod:`exposure`);
    without them all frames are taken as exposed alike.
    """
    if model != "auto" and model not in ALL_MODELS:
        raise ValueError(f"model must be auto or one of {', '.join(ALL_MODELS)}, got {model!r}")
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must have shape (F, H, W) with F >= 2, got {frames.shape}")
    shape = frames.shape[1:]
    if ignore is not None and np.shape(ignore) != shape:
        raise ValueError(f"ignore must have the frames' shape {shape}, got {np.shape(ignore)}")
    lo, hi = np.percentile(frames[0], [0.5, 99.5])
    if hi - lo <= 0:
        raise EstimationError("the reference frame is uniform: no texture to track")
    ref8 = tracking_image(frames[0], lo, hi)
    corners = find_corners(ref8, ignore=ignore)  # once per burst
    src_all = corners.reshape(-1, 2).astype(np.float64)
    candidates = ALL_MODELS if model == "auto" else [model]
    per_frame_models = [m for m in candidates if m in MODELS] or ["homography"]  # layers start from a homography
    exposures = np.ones(len(frames)) if exposures is None else exposures
    fits, per_frame, oks, dst_all = [], [], [], np.full((len(frames) - 1, len(src_all), 2), np.nan)
    for t in range(1, len(frames)):
        c = float(exposures[t])  # frame t / c is at the reference's level
        moved, ok = track_corners(ref8, tracking_image(frames[t], lo * c, hi * c), corners)
        dst_all[t - 1, ok] = moved[ok]
        oks.append(ok)
        try:
            fit, info = _fit_frame(src_all[ok], moved[ok], shape, per_frame_models)
        except EstimationError as exc:
            raise TrackingError(f"frame {t}: {exc} (each frame must show texture, overlap most of the reference "
                                "and turn less than about 10 degrees from it)") from None
        fits.append(fit)
        per_frame.append(info)
        if progress:
            progress(1)
    # surfaces that move on their own (layers) are searched for whatever the model: a point on one does so
    # in every frame, so no frame's models are fitted to it (an object that barely moves in one frame would
    # otherwise pull that frame's warp, which the frames where it moves apart do not)
    totals, base, layers = _base_and_layers(fits, per_frame, src_all, dst_all, per_frame_models, model)
    if layers.n_layers > 1:  # one layer is the base model itself
        fits, per_frame = _refit(src_all, dst_all, oks, shape, per_frame_models, layers.members > 0, fits, per_frame)
        totals, base, layers = _base_and_layers(fits, per_frame, src_all, dst_all, per_frame_models, model)
    if "layers" in candidates and (layers.n_layers > 1 or model == "layers"):
        totals["layers"] = _layers_gric(layers, per_frame, base)
    if model == "auto":
        chosen = min(totals, key=totals.get)
        reason = "lowest total GRIC: " + ", ".join(f"{m} {v:.1f}" for m, v in totals.items())
    else:
        chosen, reason = model, "forced by configuration"
    if chosen == "layers":
        warp = _layered(frames, layers, exposures)
        for t, info in enumerate(per_frame, start=1):
            kept = layers.residuals[t - 1][layers.residuals[t - 1] < INLIER_PX]  # as the other models: inliers
            info["rms"]["layers"] = float(np.sqrt(np.mean(kept**2))) if kept.size else None
    else:
        warp = _assemble(fits, chosen, shape)
    for t, info in enumerate(per_frame, start=1):
        info["rms_px"] = info.pop("rms")[chosen]
        info["displacement_px"] = trajectory_rms(warp.homographies[t], np.eye(3), shape, step=8)
        info.pop("sigma2")
    if max(f["displacement_px"] for f in per_frame) < STILL_PX:
        raise EstimationError(
            f"no motion: every frame is within {STILL_PX} px of the reference, so the gain cannot be "
            "estimated (pan or shake the camera during the burst; a scene with no texture of its own looks the same)"
        )
    described = [] if chosen != "layers" else [
        {"model": m, "points": int((layers.members == i + 1).sum())} for i, m in enumerate(layers.models)]
    return MotionResult(warp.homographies, chosen, per_frame, reason, warp, described)


def _layers_gric(layers, per_frame, base: str) -> float:
    """GRIC of the layered model, summed over frames: each point scored under its own layer, in units
    of that layer's tracking noise (points on a small, moving surface track less well: their windows
    straddle its edge), plus the parameters of every layer and a noise level per secondary layer.

    A point's layer is not counted as a parameter: like the capped residual
    of a point no model explains, it costs nothing, and :func:`layers.find_layers`
    only forms a layer from points that all follow it in every frame.
    """
    total = 0.0
    for t, info in enumerate(per_frame):
        e = layers.residuals[t]
        costs = []
        for layer in range(layers.n_layers):
            own = e[(layers.members == layer) & np.isfinite(e)]
            if own.size == 0:  # none of the layer's points tracked in this frame
                continue
            sigma2 = info["sigma2"] if layer == 0 else max(_noise_variance(own), info["sigma2"])
            costs.append(np.minimum(own**2 / sigma2, 4.0))
        params = MODEL_PARAMS[base] + layers.params + (layers.n_layers - 1)
        total += float(np.sum(np.concatenate(costs))) + params * np.log(4 * info["tracked"])
    return total


def _layered(frames: np.ndarray, layers, exposures) -> LayeredWarp:
    """The layered warp: every pixel of every frame labelled with the layer it sees, on the grid
    :func:`moving_masks` compares frames on (smoothed, reduced)."""
    factor = mask_factor(frames.shape[1:])
    smooth, to_reduced = _reduced_smooth(frames, factor, exposures)
    reduced = np.array([[to_reduced @ H @ np.linalg.inv(to_reduced) for H in per_frame]
                        for per_frame in layers.homographies])
    points = apply_homography(to_reduced, layers.points)
    labels = label_pixels(smooth, reduced, layers.members, points, smoothing=TRACK_SIGMA / factor)
    return LayeredWarp(layers.homographies, labels, to_reduced)


def _fit_frame(src, dst, shape, candidates, exclude=None) -> tuple[dict, dict]:
    """Every candidate model fitted to one frame's points; its report entry (GRIC, RMS residuals).
    Points set in the bool ``exclude`` (on a surface that moves on its own) are scored, not fitted."""
    fitted = np.flatnonzero(np.ones(len(src), bool) if exclude is None else ~exclude)
    if len(fitted) < MIN_POINTS["homography"]:
        fitted = np.arange(len(src))

    def on_all(mask: np.ndarray) -> np.ndarray:  # a mask over the fitted points, over all of them
        out = np.zeros(len(src), bool)
        out[fitted[mask]] = True
        return out

    globals_, inliers = fit_models(src[fitted], dst[fitted], shape=shape)
    inliers = on_all(inliers)
    fits: dict = {name: globals_[name] for name in MODEL_PARAMS}
    residuals = {name: transfer_residuals(H, src, dst) for name, H in fits.items()}
    used = {name: inliers for name in MODEL_PARAMS}
    params = dict(MODEL_PARAMS)
    for name in FIELD_CELLS:
        if name in candidates:
            fits[name] = fit_field(src[fitted], dst[fitted], globals_["homography"], shape, name)
            residuals[name] = field_residuals(fits[name], src, dst, shape)
            # a fit with too few points keeps none: judge it on all it was fitted to
            keep = fits[name].keep
            used[name] = on_all(keep if keep.any() else np.ones(len(fitted), bool))
            params[name] = fits[name].dof
    # the tracking noise: the smallest any candidate reaches on the points it keeps
    sigma2 = max(min(_noise_variance(residuals[m][used[m]]) for m in candidates), 1e-8)
    scores = gric({m: residuals[m] for m in candidates}, params, sigma2)
    rms = {m: float(np.sqrt(np.mean(residuals[m][used[m]] ** 2))) for m in candidates}
    info = {"tracked": int(len(src)), "inliers": int(inliers.sum()), "gric": scores, "rms": rms, "sigma2": sigma2}
    return fits, info


def _base_and_layers(fits, per_frame, src, dst, candidates, model: str) -> tuple[dict, str, object]:
    """Each per-frame model's GRIC summed over frames; the global model layers are split off from
    (the best one under ``auto``, else a homography); and the layers (:func:`layers.find_layers`)."""
    totals = {name: sum(f["gric"][name] for f in per_frame) for name in candidates}
    base = min(MODEL_PARAMS, key=lambda m: totals[m]) if model == "auto" else "homography"
    return totals, base, find_layers(src, dst, np.array([np.eye(3)] + [f[base] for f in fits]))


def _refit(src, dst, oks, shape, candidates, exclude, fits, per_frame) -> tuple[list, list]:
    """Each frame's models fitted again without the points set in ``exclude``; a frame keeps its fit
    where too few points are left."""
    out_fits, out_info = [], []
    for t, ok in enumerate(oks):
        try:
            fit, info = _fit_frame(src[ok], dst[t, ok], shape, candidates, exclude=exclude[ok])
        except EstimationError:
            fit, info = fits[t], per_frame[t]
        out_fits.append(fit)
        out_info.append(info)
    return out_fits, out_info


def _assemble(fits: list[dict], chosen: str, shape) -> GlobalWarp | FieldWarp:
    """The warp of the chosen model from each frame's fits (the reference: identity, no field)."""
    if chosen in MODEL_PARAMS:
        return GlobalWarp(np.array([np.eye(3)] + [f[chosen] for f in fits]))
    first = fits[0][chosen].coefficients
    coefficients = np.zeros((len(fits) + 1,) + first.shape)
    coefficients[1:] = [f[chosen].coefficients for f in fits]
    return FieldWarp(np.array([np.eye(3)] + [f[chosen].H for f in fits]), coefficients, tuple(shape))


# ---------------------------------------------------------------------------
# what does not follow the global motion

#: A pixel does not follow the global warp when its dense (DIS) flow departs
#: from the warp by more than MASK_FLOW_PX *and* the frames disagree there by
#: more than MASK_SIGMAS robust standard deviations (after TRACK_SIGMA
#: smoothing): flow alone is unreliable on flat areas, where a wrong vector
#: costs nothing anyway. The disagreement is relative to the brightness (at
#: least MASK_FLOOR x the median), as the gain pattern is: measured in
#: absolute DN, bright flat areas were flagged for their FPN. The mask is
#: then grown by MASK_GROW_PX. Measured on 200x260x6 bursts, seeds 3-8, both
#: scenes, shake and 25 px drift, true motion (absolute at 4 sigmas ->
#: relative at 3.5): textured object pixels found in the worst frame of the
#: drift bursts 94-97 % either way (in the shake bursts some seed's worst
#: frame finds none either way); without an object, flagged 0.2-1.6 % ->
#: 0.1-1.1 % of the burst and at most 7.2 % -> 2.7 % of the reference.
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


def _reduced_smooth(frames: np.ndarray, factor: int, exposures=None) -> tuple[list, np.ndarray]:
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

    ``motion`` is a warp of :mod:`trajectory` or ``(F, 3, 3)`` homographies.
    Frame t (t >= 1) is compared with the reference: DIS flow from t to the
    reference against the motion's prediction, and the smoothed brightness of
    the two. The reference's own mask is the union of its comparisons with
    every frame. The comparison runs on frames reduced ``factor`` times
    (default :func:`mask_factor`), each divided by its exposure relative to
    the reference (``exposures``; none: all alike). Returns bool ``(F, H, W)``.
    """
    import cv2

    from .warp import positions, sample

    frames = np.asarray(frames, np.float32)
    n, h, w = frames.shape
    factor = mask_factor((h, w)) if factor is None else int(factor)
    lo, hi = np.percentile(frames[0], [0.5, 99.5])
    smooth, to_reduced = _reduced_smooth(frames, factor, exposures)
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
        sigma = 1.4826 * float(np.median(diff[::2, ::2]))  # a robust spread: a quarter of the pixels suffice
        # a pixel frame b does not see (outside it, or hidden in it under a layered warp:
        # trajectory.NOWHERE) is compared with nothing, so it departs from nothing
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


def trajectory_rms(H_est: np.ndarray, H_true: np.ndarray, shape: tuple[int, int], step: int = 4) -> float:
    """RMS distance (px) between where two homographies send the reference's pixels."""
    h, w = shape
    ys, xs = np.mgrid[0:h:step, 0:w:step].astype(np.float64)
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    a, b = H_est @ p, H_true @ p
    return float(np.sqrt(np.mean(np.sum((a[:2] / a[2] - b[:2] / b[2]) ** 2, axis=0))))
