"""The motion of a burst: every frame tracked against the reference, each model fitted frame by
frame, and the one with the lowest GRIC chosen (or scene layers found).

Conventions (docs/method.md): arrays are ``(row, col)``; points are ``(x, y)``; ``H_t_ref``
maps reference pixel coordinates to frame ``t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import EstimationError, TrackingError
from ..geometry.warps import STILL_PX, FieldWarp, GlobalWarp, LayeredWarp, apply_homography, trajectory_rms
from ..metrics import point_noise_variance
from . import ALL_MODELS as _ALL_NAMES
from . import MODELS as _NAMES
from .fields import FIELD_CELLS, fit_field
from .fields import residuals as field_residuals
from .fit import INLIER_PX, MIN_POINTS, MODEL_PARAMS, fit_models, gric, transfer_residuals
from .layers import find_layers, label_pixels
from .masks import mask_factor, reduced_smooth
from .track import TRACK_SIGMA, find_corners, track_corners, tracking_image

#: The models' names (:mod:`motion`): those fitted frame by frame (:data:`fit.MODEL_PARAMS`, then
#: :data:`fields.FIELD_CELLS`), and all of them with the layers.
MODELS, ALL_MODELS = list(_NAMES), list(_ALL_NAMES)


@dataclass(frozen=True)
class FrameFit:
    """One frame's fit: corners tracked from the reference and the inliers kept, the residual
    under the chosen model on them (None where it kept none), the frame's RMS displacement from
    the reference, each model's GRIC (lower is better), and where the chosen model is a global
    one simpler than a homography, its RMS distance from the homography fitted to the same
    points (over the frame: how much motion the simpler model leaves out)."""

    tracked: int
    inliers: int
    rms_px: float | None
    displacement_px: float
    gric: dict
    misfit_px: float | None = None


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
    per_frame : list of FrameFit
        Every frame's but the reference's.
    reason : str
        Why that model was chosen.
    warp : GlobalWarp, FieldWarp or LayeredWarp
        The motion as maps between frames.
    layers : list of tuple
        For the layers model: each secondary layer's model and point count.
    """

    homographies: np.ndarray
    model: str
    per_frame: list = field(default_factory=list)
    reason: str = ""
    warp: GlobalWarp | FieldWarp | LayeredWarp | None = None
    layers: list = field(default_factory=list)






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
    field models (:mod:`motion.fields`) are fitted to them, and scene layers
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
    simpler = chosen in MODEL_PARAMS and chosen != "homography"
    per_frame = [FrameFit(info["tracked"], info["inliers"], info["rms"][chosen],
                          trajectory_rms(warp.homographies[t], np.eye(3), shape, step=8), info["gric"],
                          trajectory_rms(fit[chosen], fit["homography"], shape, step=8) if simpler else None)
                 for t, (info, fit) in enumerate(zip(per_frame, fits), start=1)]
    if max(f.displacement_px for f in per_frame) < STILL_PX:
        raise EstimationError(
            f"no motion: every frame is within {STILL_PX} px of the reference, so the gain cannot be "
            "estimated (pan or shake the camera during the burst; a scene with no texture of its own looks the same)"
        )
    described = [] if chosen != "layers" else [
        (m, int((layers.members == i + 1).sum())) for i, m in enumerate(layers.models)]
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
            sigma2 = info["sigma2"] if layer == 0 else max(point_noise_variance(own), info["sigma2"])
            costs.append(np.minimum(own**2 / sigma2, 4.0))
        params = MODEL_PARAMS[base] + layers.params + (layers.n_layers - 1)
        total += float(np.sum(np.concatenate(costs))) + params * np.log(4 * info["tracked"])
    return total


def _layered(frames: np.ndarray, layers, exposures) -> LayeredWarp:
    """The layered warp: every pixel of every frame labelled with the layer it sees, on the grid
    :func:`moving_masks` compares frames on (smoothed, reduced)."""
    factor = mask_factor(frames.shape[1:])
    smooth, to_reduced = reduced_smooth(frames, factor, exposures)
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
    sigma2 = max(min(point_noise_variance(residuals[m][used[m]]) for m in candidates), 1e-8)
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
