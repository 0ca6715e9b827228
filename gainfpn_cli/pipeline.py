"""Burst + config -> gain map: the only place config sections are unpacked.

``estimate`` runs motion, the solver and the FPN model on every plane of a
burst (:mod:`geometry.planes`) and checks the result on a held-out frame.
"""

from __future__ import annotations

import dataclasses
import platform
import time
from dataclasses import dataclass

import numpy as np

from . import __version__
from .burst import Estimate, LoadedBurst, Progress
from .config import Config, config_dict
from .errors import EstimationError, InputError, TrackingError
from .files import check_consistent, find_frames, read_frame, stamp
from .geometry.planes import frame_homography, motion_frames, plane_views, reference_cells, solve_grids
from .geometry.resample import positions as warp_positions
from .motion.estimate import estimate_motion
from .motion.exposure import relative_exposures, rough_exposures, significant
from .motion.masks import moving_masks
from .report import Exposure, FrameMotion, Holdout, Layer, Motion, PlaneCheck, PlaneReport, Prnu, Report
from .solve.accurate import AccurateOptions, power_of_two_scale, solve_accurate
from .solve.blocks import solve_paper
from .solve.fpnmodel import select_model
from .solve.holdout import holdout_checks, pooled
from .solve.kkt import SolveOptions
from .solve.result import GainResult, physical, sigma_from_confidence

#: Fewest frames a burst needs; the hold-out check needs one more, since a
#: fit on 2 frames is never trusted. Measured: 2 frames, residual FPN 7.5-11 %
#: from 5 % (64x80); 3 frames unchecked, 1.1-1.3 % on 64x80 but 2.9 % and
#: an MSE ratio of 0.9x on 640x480 (bench, frames group).
MIN_FRAMES = 3
#: Fewest pixels per side of the images motion is tracked on (measured: 48 px
#: frames lose frames to too few inliers; 64 px work).
MIN_TRACK_SIDE = 64
#: Fraction of the reference's pixels at or below black above which the estimate warns that the
#: burst is read-noise limited (a warning: a scene with deep shadows crosses it too; docs/limits.md).
MAX_DARK_FRACTION = 0.01


def _check_frame_count(n: int, error: type, where: str = "") -> None:
    """Refuse bursts of fewer than :data:`MIN_FRAMES` (``error`` says whose fault it is)."""
    if n < MIN_FRAMES:
        raise error(f"need at least {MIN_FRAMES} frames, got {n}{where}: with 2, each pixel is compared along a "
                    "single chain of pixels whose errors add up (measured: worse than no correction)")


def load_burst(inputs, cfg: Config, *, progress: Progress | None = None) -> LoadedBurst:
    """Read the frames (and subtract the master dark frame) as one float32 stack."""
    paths = find_frames(inputs)
    _check_frame_count(len(paths), InputError, f" ({paths[0] if paths else 'none'})")
    if cfg.input.reference >= len(paths):
        raise InputError(f"input.reference is {cfg.input.reference} but there are only {len(paths)} frames")
    t0 = time.perf_counter()
    update = progress("read", len(paths)) if progress else None
    infos, stamps = [], []
    stack = None
    for i, path in enumerate(paths):  # into one preallocated stack: the frames are held once
        frame = read_frame(path)
        infos.append(frame.info)
        check_consistent(infos)
        stamps.append(stamp(path))
        if stack is None:
            stack = np.empty((len(paths),) + frame.data.shape, np.float32)
        stack[i] = frame.data
        if update:
            update(1)
    info = infos[0]
    dark_stamp = None
    if cfg.input.dark is not None:
        dark = read_frame(cfg.input.dark)
        if dark.data.shape != stack.shape[1:]:
            raise InputError(f"{cfg.input.dark}: dark frame is {dark.data.shape[1]}x{dark.data.shape[0]} with "
                             f"{dark.data.shape[2]} channel(s); the frames are {stack.shape[2]}x{stack.shape[1]} "
                             f"with {stack.shape[3]}")
        stack -= dark.data[None]
        dark_stamp = stamp(cfg.input.dark)
    saturation = cfg.input.saturation if cfg.input.saturation is not None else info.saturation
    return LoadedBurst(paths, stack, info.cfa, info.channels, saturation, cfg.input.reference, tuple(stamps),
                       dark_stamp, time.perf_counter() - t0, info.layout()[4])


def estimate(burst: LoadedBurst, cfg: Config, *, progress: Progress | None = None, executor=None) -> Estimate:
    """Motion, solve and FPN model for every plane; the hold-out check; a report.

    The solver's tasks run on ``cfg.solver.workers`` local processes, or on ``executor`` (a
    :class:`parallel.DaskExecutor`). BLAS and OpenMP run single-threaded meanwhile
    (:func:`parallel.single_threaded_math`), whoever calls, so every caller gets the command's
    speed and bit-identical results."""
    from .parallel import single_threaded_math

    solver = _Solver.from_config(cfg.solver, mosaic=burst.cfa is not None, executor=executor)
    with single_threaded_math():
        return _estimate(burst, cfg, solver, progress)


@dataclass(frozen=True)
class _Solver:
    """The solver section of the config, unpacked once per estimate into the solvers' options."""

    method: str
    paper: SolveOptions
    block_size: int
    accurate: AccurateOptions
    fpn_model: str | None  # None: chosen by AIC
    gain_range: tuple[float, float]
    workers: int
    executor: object = None

    @classmethod
    def from_config(cls, s, *, mosaic: bool, executor=None) -> "_Solver":
        accurate = AccurateOptions(kernel=s.interpolation, anchors=s.anchors, partners=s.partners, rtol=s.rtol,
                                   gauge_sigma=s.gauge_sigma, tile=s.tile, robust_rounds=s.robust_rounds,
                                   gain_range=s.gain_range,
                                   phase_weights=s.phase_weights == "all" or (s.phase_weights == "auto" and mosaic))
        return cls(s.method, SolveOptions(lam=s.lam, max_condition=s.max_condition, k_range=s.gain_range),
                   s.block_size, accurate, None if s.fpn_model == "auto" else s.fpn_model, s.gain_range, s.workers,
                   executor)


def _estimate(burst: LoadedBurst, cfg: Config, solver: _Solver, progress: Progress | None) -> Estimate:
    timings: dict[str, float] = {}
    warnings: list[str] = []
    order = [burst.reference] + [i for i in range(len(burst.paths)) if i != burst.reference]
    _check_frame_count(len(order), EstimationError)
    dark = float(np.mean(burst.frames[burst.reference] <= 0))
    if dark > MAX_DARK_FRACTION:
        warnings.append(f"the frames are dark: {100 * dark:.1f} % of the reference's pixels are at or below black; "
                        "near black the estimate is noise-limited and biased, and where most of the frame is this "
                        "dark it can be worse than no correction (expose longer or raise the sensor gain)")
    # reference first: the frames as loaded when it is (no copy: the solver leaves out the pixels
    # masked as moving itself, and scales its tiles where the float32 products need it)
    frames = burst.frames if order == list(range(len(order))) else burst.frames[order]
    holdout = cfg.output.holdout
    if holdout and len(frames) <= MIN_FRAMES:
        raise EstimationError(f"only {len(frames)} frames: holding one out to check the estimate would leave "
                              f"{len(frames) - 1} to fit, which does worse than no correction; capture more frames, "
                              "or set output.holdout: false to fit all of them unchecked")
    if not holdout:
        warnings.append("output.holdout is off: no frame checks the estimate")
    fit_frames = frames[:-1] if holdout else frames

    t0 = time.perf_counter()
    motion_images, S_motion = motion_frames(frames, burst.cfa)
    if min(motion_images.shape[1:]) < MIN_TRACK_SIDE:
        binned = " after 2x2 CFA binning" if burst.cfa else ""
        raise EstimationError(f"frames of {frames.shape[2]}x{frames.shape[1]} px are too small to track motion "
                              f"(need at least {MIN_TRACK_SIDE} px per side{binned})")
    update = progress("motion", len(frames) - 1) if progress else None
    motion, exposures, exposure_report = _track(motion_images, burst, cfg, update)
    in_frame = motion.warp.conjugate(np.linalg.inv(S_motion))  # the motion in frame pixels
    excluded, moving = _moving(frames, motion_images, motion.warp, burst.cfa, cfg, exposures)
    del motion_images
    timings["motion_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_fit = len(fit_frames)
    k, confidence, plane_reports = _solve_planes(burst, frames, excluded, exposures, slice(0, n_fit), in_frame, solver,
                                                 progress)
    for round_ in range(1, cfg.motion.refine_rounds + 1):
        corrected, _ = motion_frames(frames * (k / np.float32(power_of_two_scale(frames[0])))[None], burst.cfa)
        # the model is chosen again: on frames without their gain pattern the choice can change (a forced
        # "layers" would also lose the base model auto chose for it)
        ignore = reference_cells(excluded, corrected.shape[1:], burst.cfa)  # no corner on what the round masked
        motion = estimate_motion(corrected, model=cfg.motion.model, ignore=ignore, exposures=exposures)
        reason = f"{motion.reason}; refined on frames corrected by k (round {round_})"
        motion = dataclasses.replace(motion, reason=reason)
        in_frame = motion.warp.conjugate(np.linalg.inv(S_motion))
        excluded, moving = _moving(frames, corrected, motion.warp, burst.cfa, cfg, exposures)
        del corrected
        k, confidence, plane_reports = _solve_planes(burst, frames, excluded, exposures, slice(0, n_fit), in_frame,
                                                     solver, progress)
    timings["solve_s"] = time.perf_counter() - t0

    holdout_report = None
    if holdout:
        holdout_report, failed = _check(burst, frames, excluded, exposures, n_fit, in_frame, solver, plane_reports,
                                        progress, burst.paths[order[-1]].name, k, confidence)
        timings["holdout_s"] = time.perf_counter() - t0 - timings["solve_s"]
        for grid in failed:
            grid.scatter(k, np.ones_like(grid.gather(k)))
            grid.scatter(confidence, np.zeros_like(grid.gather(confidence)))
        if failed:
            warnings.append(_rejection(holdout_report, failed))
    sigma = sigma_from_confidence(confidence)
    # only the accurate solver's confidence is a calibrated standard error
    calibrated = (confidence > 0).any() and all(p.method == "accurate" for p in plane_reports.values())
    report = Report(
        prnu_percent=Prnu.combined({name: p.input_fpn_percent for name, p in plane_reports.items()
                                    if p.input_fpn_percent is not None}),
        predicted_residual_percent=float(100 * np.median(sigma[confidence > 0])) if calibrated else None,
        holdout=holdout_report,
        estimated_percent=float(100 * (confidence > 0).mean()),
        inputs=burst.stamps,
        dark=burst.dark,
        white_level_dn=burst.white,
        reference=burst.paths[burst.reference].name,
        motion=Motion(
            model=motion.model,
            reason=motion.reason,
            layers=tuple(Layer(model, points) for model, points in motion.layers),
            frames=tuple(FrameMotion(burst.paths[order[i + 1]].name, f.tracked, f.inliers, f.rms_px, f.displacement_px,
                                     frame_homography(motion.homographies[i + 1], S_motion))
                         for i, f in enumerate(motion.per_frame)),
            refine_rounds=cfg.motion.refine_rounds,
            moving_percent=moving,
        ),
        exposure=exposure_report,
        planes=plane_reports,
        config=config_dict(cfg),
        timings={"read_s": burst.read_s, **timings},
        versions=_versions(),
        warnings=tuple(warnings),
    )
    return Estimate(k.astype(np.float32), confidence.astype(np.float32), report)


def _track(motion_images, burst, cfg, progress) -> tuple:
    """The motion of the burst, each frame's exposure relative to the reference and what the report
    says of them. Frames are tracked as exposed alike first; where their exposures turn out to
    differ, again at the reference's level; frames too differently exposed to track at all, again
    at their median's level before their exposures are measured."""
    try:
        motion = estimate_motion(motion_images, model=cfg.motion.model, progress=progress)
    except TrackingError:
        rough = rough_exposures(motion_images)
        if cfg.input.exposure == "fixed" or np.max(np.abs(rough - 1.0)) <= ROUGH_EXPOSURE:
            raise
        # a 10 % jump loses nearly every track
        motion = estimate_motion(motion_images, model=cfg.motion.model, exposures=rough)
    exposures, report = _exposures(motion_images, motion.warp, burst, cfg)
    if np.max(np.abs(exposures - 1.0)) > RETRACK_EXPOSURE:
        motion = estimate_motion(motion_images, model=cfg.motion.model, exposures=exposures)
        exposures, report = _exposures(motion_images, motion.warp, burst, cfg)
    return motion, exposures, report


def _moving(frames, motion_images, warp, cfa, cfg, exposures) -> tuple[np.ndarray | None, list[float] | None]:
    """Pixels of each frame that do not follow the estimated motion, ``(F, H, W)`` bool, which
    the solvers leave out; and the percentage of each frame's pixels. None without ``mask_moving``.
    A CFA's masks (on 2x2 cells) are brought to photosites one frame at a time."""
    if not cfg.motion.mask_moving:
        return None, None
    masks = moving_masks(motion_images, warp, exposures=exposures)
    if cfa:  # grey-proxy pixel (y, x) is the CFA cell of photosites (2y.., 2x..)
        cells, masks = masks, np.empty(frames.shape[:3], bool)
        for t, mask in enumerate(cells):
            mask = np.repeat(np.repeat(mask, 2, axis=0), 2, axis=1)
            masks[t] = np.pad(mask, [(0, frames.shape[1] - mask.shape[0]), (0, frames.shape[2] - mask.shape[1])],
                              mode="edge")
        del cells
    return masks, [round(100 * float(m.mean()), 2) for m in masks]


#: Frames are tracked again, each at the reference's brightness, when one's
#: exposure (a significant one: :func:`exposure.significant`) differs from
#: the reference's by more than this fraction.
RETRACK_EXPOSURE = 0.002
#: When the frames cannot be tracked alike, they are tracked again each at the
#: reference's level by its median (:func:`exposure.rough_exposures`) if one's
#: differs by more than this fraction.
ROUGH_EXPOSURE = 0.02


def _exposures(motion_images, warp, burst, cfg) -> tuple[np.ndarray, Exposure]:
    """Each frame's exposure relative to the reference (:mod:`exposure`), measured on the motion
    images (a CFA's 2x2 cells: a clipped photosite lowers its cell, the median shrugs a few off)
    and kept where it differs from 1 significantly; all ones with ``input.exposure: fixed``. And
    what the report says of them."""
    if cfg.input.exposure == "fixed":
        return np.ones(len(motion_images)), Exposure("fixed")
    measured, errors = relative_exposures(motion_images, warp, saturation=burst.saturation)
    used = significant(measured, errors)
    return used, Exposure("per-frame", tuple(round(float(c), 6) for c in used),
                          tuple(round(float(c), 6) for c in measured),
                          tuple(float(e) if np.isfinite(e) else None for e in errors))


def _grids(burst: LoadedBurst, frames: np.ndarray, method: str) -> list:
    """The grids the solver runs on (the accurate solver takes a CFA's two greens together)."""
    return list(solve_grids(burst.cfa, burst.channels, frames.shape[1:3], greens_together=method == "accurate"))


def _solve_planes(burst, frames, excluded, exposures, used: slice, in_frame, solver: _Solver, progress, *,
                  regions: dict | None = None, models: dict | None = None):
    """k and confidence of every plane from the frames ``used``, with the FPN model and the gauge.

    ``regions`` (grid name -> (rows, columns) slices) solves only there (k = 1 and confidence 0
    elsewhere); ``models`` (plane name -> FPN model) forces each plane's model."""
    k = np.ones(frames.shape[1:], np.float32)
    confidence = np.zeros(frames.shape[1:], np.float32)
    fit = frames[used]  # a slice: a view
    left_out = None if excluded is None else np.broadcast_to(excluded[used, ..., None], fit.shape)  # every channel
    motion = in_frame.select(range(len(frames))[used])
    solved = {}
    for grid in _grids(burst, frames, solver.method):
        grid_frames, grid_left_out, grid_motion = grid.gather(fit), None, motion.conjugate(grid.S)
        if left_out is not None:
            grid_left_out = grid.gather(left_out)
        if regions is not None:
            rows, columns = regions[grid.name]
            grid_frames = grid_frames[:, rows, columns]
            grid_left_out = None if grid_left_out is None else grid_left_out[:, rows, columns]
            grid_motion = grid_motion.conjugate(np.array([[1.0, 0, columns.start], [0, 1.0, rows.start], [0, 0, 1]]))
        result = _solve_grid(grid_frames, grid_left_out, grid_motion, burst.saturation, solver, progress, grid.name,
                             exposures=exposures[used])
        grid_k, grid_confidence = result.k, result.confidence
        if regions is not None:
            grid_k, grid_confidence = np.ones_like(grid.gather(k)), np.zeros_like(grid.gather(confidence))
            grid_k[rows, columns], grid_confidence[rows, columns] = result.k, result.confidence
        grid.scatter(k, grid_k)
        grid.scatter(confidence, grid_confidence)
        solved.update({name: PlaneReport(solver.method, grid.name, result.stats) for name in grid.positions})
    reports = {}
    for name, pick, _ in plane_views(burst.cfa, burst.channels):  # the gauge and the FPN model, plane by plane
        report, structured = solved[name], False
        kp = pick(k)
        if solver.method == "accurate":
            model = select_model(kp, pick(confidence), force=(models or {}).get(name) or solver.fpn_model)
            report = dataclasses.replace(report, fpn_model=model.chosen, fpn_model_aic=model.scores,
                                         input_fpn_percent=model.split)
            kp, structured = model.k, model.chosen not in ("pixel", "none")
        result = physical(GainResult(kp, pick(confidence)), solver.gain_range, structured)
        pick(k)[...] = result.k
        pick(confidence)[...] = result.confidence
        reports[name] = report
    return k, confidence, reports


#: Side (px of each grid) of the central region the hold-out check fits again without the reference:
#: enough blocks for a standard error of the ratio near 1 % (256 blocks of 16 px), at a small cost
#: on large frames (a 12 MP mosaic's planes are 2000 px wide).
CHECK_SIDE = 256
#: The hold-out check keeps a plane's estimate only where its residual ratio is below 1 by this many
#: standard errors (one-sided, about 2 % of estimates that do not help would pass by chance).
CHECK_Z = 2.0


def _check(burst, frames, excluded, exposures, n_fit, in_frame, solver: _Solver, reports, progress, held_out: str,
           k, confidence):
    """The hold-out check (:mod:`solve.holdout`) of the map ``k`` (``confidence``) of every grid on the
    frame named ``held_out``, and the grids it rejects.

    k is fitted again on the central :data:`CHECK_SIDE` px of each grid, from the fitted frames
    without the reference and with each plane's FPN model as chosen, so that neither frame the
    check compares is in it."""
    grids = _grids(burst, frames, solver.method)
    regions = {}
    for grid in grids:
        h, w = grid.gather(frames[0]).shape
        y0, x0 = max(0, (h - CHECK_SIDE) // 2), max(0, (w - CHECK_SIDE) // 2)
        regions[grid.name] = (slice(y0, min(h, y0 + CHECK_SIDE)), slice(x0, min(w, x0 + CHECK_SIDE)))
    k_check, confidence_check, _ = _solve_planes(
        burst, frames, excluded, exposures, slice(1, n_fit), in_frame, solver, progress, regions=regions,
        models={name: p.fpn_model for name, p in reports.items()})
    checks = holdout_checks(frames, excluded, exposures, in_frame, k_check, grids=grids, saturation=burst.saturation,
                            regions=regions, disagreement=_disagreement(k_check, confidence_check, k, confidence,
                                                                        calibrated=solver.method == "accurate"))
    failed = [grid for grid in grids if not checks[grid.name].passed(CHECK_Z)]
    every = pooled(checks.values())
    planes = {name: PlaneCheck(c.ratio, c.standard_error, c.passed(CHECK_Z), c.left_out) for name, c in checks.items()}
    return Holdout(held_out, every.ratio, len(failed) < len(grids), every.standard_error, planes), failed


def _disagreement(k_check, confidence_check, k, confidence, *, calibrated: bool) -> np.ndarray:
    """``(k_check - k)^2``, in the two maps' combined variance where their confidence is a standard
    error (``calibrated``; the paper's block solver has none); 0 where either is unestimated."""
    both = (confidence_check > 0) & (confidence > 0)
    squared = np.where(both, k_check - k, np.float32(0)) ** 2
    if calibrated:
        variance = sigma_from_confidence(np.where(both, confidence_check, 1)) ** 2 \
            + sigma_from_confidence(np.where(both, confidence, 1)) ** 2
        squared = np.where(both, squared / np.maximum(variance, np.float32(1e-12)), np.float32(0))
    return squared


def _rejection(holdout: Holdout, failed) -> str:
    """The warning of planes the hold-out check rejected: what was written, why, and what would help."""
    which = "the estimate" if len(failed) == len(holdout.planes) else "the " + ", ".join(g.name for g in failed)
    ratios = ", ".join(f"{g.name} {holdout.planes[g.name].residual_ratio:.3f} +- "
                       f"{holdout.planes[g.name].standard_error:.3f}" for g in failed)
    return (f"the hold-out frame does not confirm {which} (residual ratio with k over without: {ratios}; a "
            f"correction is kept only below 1 by {CHECK_Z:g} standard errors), so k = 1 (no correction) was written "
            f"there: the burst is too noisy or too aliased for its gain pattern; more frames, more light or more "
            f"motion would help")


def _solve_grid(frames, excluded, motion, saturation, solver: _Solver, progress, name,
                exposures=None) -> GainResult:
    update = progress(f"solve {name}", 0) if progress else None
    if solver.method == "paper":
        if excluded is not None:  # the published form takes zeroed pixels as missing
            frames = np.where(excluded, np.float32(0), frames)
        if exposures is not None and np.any(exposures != 1.0):  # clipped pixels marked missing before scaling
            if saturation is not None:
                frames = np.where(frames >= saturation, np.float32(0), frames)
            frames = frames / np.asarray(exposures, np.float32)[:, None, None]
        region = (0, 0) + frames.shape[1:]
        positions = np.stack([warp_positions(motion.pair(0, t, region), frames.shape[1:])
                              for t in range(1, len(frames))])
        return solve_paper(frames, positions, block_size=solver.block_size, options=solver.paper,
                           saturation=saturation, workers=solver.workers, progress=update, executor=solver.executor)
    return solve_accurate(frames, motion, options=solver.accurate, saturation=saturation, excluded=excluded,
                          exposures=exposures, workers=solver.workers, progress=update, executor=solver.executor)


def _versions() -> dict:
    import cv2
    import OpenImageIO
    import rawpy
    import scipy

    return {"gainfpn": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "opencv": cv2.__version__, "openimageio": OpenImageIO.__version__,
            "rawpy": rawpy.__version__}
