"""Burst + config -> gain map: the only place config sections are unpacked.

``estimate`` runs motion, the solver and the FPN model on every plane of a
burst (:mod:`geometry.planes`) and checks the result on a held-out frame.
"""

from __future__ import annotations

import dataclasses
import platform
import time

import numpy as np

from . import __version__, checking, choosing, darkness, defective, solving
from .burst import Estimate, LoadedBurst, Progress
from .config import Config, config_dict
from .errors import EstimationError, InputError, TrackingError
from .files import check_consistent, find_frames, read_frame, stamp
from .geometry.planes import frame_homography, motion_frames, reference_cells
from .motion.estimate import estimate_motion
from .motion.exposure import relative_exposures, rough_exposures, significant
from .motion.masks import moving_masks
from .report import Defects, Exposure, FrameMotion, Layer, Motion, Prnu, Report
from .solve.result import sigma_from_confidence
from .solve.tiling import power_of_two_scale
from .solving import CALIBRATED_METHODS

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
#: Warned where ``solver.method: scene`` is set on a CFA mosaic (``auto`` never takes it there). Measured
#: on 640x480x16 and 480x360x16 raw12 bursts of the photograph `astronaut`: a smooth gain error of
#: 9-13 % over a dark corner, frame 0's MSE 8.3x and 16x worse, every kept plane passed by the
#: hold-out check (docs/limits.md, "The scene solver").
SCENE_ON_MOSAIC = ("solver.method is scene on a CFA mosaic: each colour plane sees the scene only every other "
                   "photosite, and where a plane is dark its map can carry a smooth gain error that the hold-out "
                   "frame cannot show (a small shake barely observes it); solver.method auto uses the accurate "
                   "solver on mosaics")
#: RMS distance (px of the tracked images) past which a forced motion model simpler than a
#: homography is refused: the frames move in a way it leaves out, so the map would be fitted to
#: misaligned frames, and the hold-out frame, aligned the same way, cannot tell. Measured on
#: 96x128 to 640x480 bursts: 0.002-0.047 px where the forced model is the true one (the
#: homography's own noise; 0.047 an affine on a 1-degree rotation), 0.67-5.3 px for a translation
#: on bursts rotating 0.3-1 degree. Not measured on larger frames.
MAX_MISFIT_PX = 0.1


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
    dark_stamp = dark_hot = None
    if cfg.input.dark is not None:
        dark = read_frame(cfg.input.dark)
        if dark.data.shape != stack.shape[1:]:
            raise InputError(f"{cfg.input.dark}: dark frame is {dark.data.shape[1]}x{dark.data.shape[0]} with "
                             f"{dark.data.shape[2]} channel(s); the frames are {stack.shape[2]}x{stack.shape[1]} "
                             f"with {stack.shape[3]}")
        stack -= dark.data[None]
        dark_stamp = stamp(cfg.input.dark)
        if cfg.input.defects:
            dark_hot = defective.hot_in_dark(dark.data, info.cfa, info.channels)
    saturation = cfg.input.saturation if cfg.input.saturation is not None else info.saturation
    return LoadedBurst(paths, stack, info.cfa, info.channels, saturation, cfg.input.reference, tuple(stamps),
                       dark_stamp, time.perf_counter() - t0, info.layout()[4], dark_hot)


def estimate(burst: LoadedBurst, cfg: Config, *, progress: Progress | None = None, executor=None) -> Estimate:
    """Motion, solve and FPN model for every plane; the hold-out check; a report.

    The solver's tasks run on ``cfg.solver.workers`` local processes, or on ``executor`` (a
    :class:`parallel.DaskExecutor`). BLAS and OpenMP run single-threaded meanwhile
    (:func:`parallel.single_threaded_math`), whoever calls, so every caller gets the command's
    speed and bit-identical results."""
    from .parallel import single_threaded_math

    solver = solving.Solver.from_config(cfg.solver, mosaic=burst.cfa is not None, defects=cfg.input.defects,
                                        executor=executor)
    with single_threaded_math():
        return _estimate(burst, cfg, solver, progress)


def _estimate(burst: LoadedBurst, cfg: Config, solver: solving.Solver, progress: Progress | None) -> Estimate:
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
    names = [burst.paths[i].name for i in order[1:]]
    if cfg.motion.model != "auto":  # auto weighs what a simpler model leaves out against its noise (GRIC)
        _check_misfit(motion, names, S_motion)
    in_frame = motion.warp.conjugate(np.linalg.inv(S_motion))  # the motion in frame pixels
    excluded, moving = _moving(frames, motion_images, motion.warp, burst.cfa, cfg, exposures)
    del motion_images
    timings["motion_s"] = time.perf_counter() - t0
    codes = None
    if cfg.input.defects or cfg.solver.min_snr > 0:  # the search measures the readings' noise too
        t0 = time.perf_counter()
        found = defective.find(frames, burst.cfa, burst.channels, excluded=excluded, exposures=exposures,
                               warp=in_frame, saturation=burst.saturation, dark_hot=burst.dark_hot,
                               latent=cfg.input.defects and cfg.input.defects_latent,
                               threads=cfg.solver.workers)  # the workers' CPUs, idle until the solve
        codes = found.codes if cfg.input.defects else None
        if cfg.solver.min_snr > 0:
            floors = darkness.floors(found.noise, cfg.solver.min_snr, burst.saturation)
            solver = dataclasses.replace(solver, floors=floors, noise=found.noise)
        timings["defects_s"] = time.perf_counter() - t0

    # the defects' readings are replaced from their neighbours while they are solved and checked
    with defective.repaired(frames, codes, burst.cfa, burst.channels):
        n_fit = len(fit_frames)
        t0 = time.perf_counter()
        solver, choice = choosing.choose(burst, frames, excluded, exposures, slice(0, n_fit), in_frame, solver)
        if solver.method == "scene" and burst.cfa is not None:
            warnings.append(SCENE_ON_MOSAIC)
        chosen_s = time.perf_counter() - t0
        fit = _Fit(motion, in_frame, excluded, moving)
        held_out = burst.paths[order[-1]].name if holdout else None
        tried = [_solve(burst, frames, exposures, n_fit, fit, dataclasses.replace(solver, method=method), cfg, names,
                        S_motion, progress, held_out) for method in (choice.tried if holdout else ())]
        if tried:  # the one with the lower expected error (both calibrated; the held-out frame's ratio ranks
            # them worse on dark bursts, docs/method.md 8c), where the check confirms the first (the accurate
            # solver's) at all: on data that weak, with few frames, the scene solver's sigma_k is not calibrated
            confirmed = not tried[0].failed
            fpn = _pixel_fpn(tried[0].reports)
            errors = {t.solver.method: choosing.expected_error(t.confidence, frames[0], fpn) for t in tried}
            solved = min(tried, key=lambda t: errors[t.solver.method]) if confirmed else tried[0]
            choice = choosing.tried(choice, {t.solver.method: t.holdout.residual_ratio for t in tried}, errors,
                                   solved.solver.method, confirmed)
        else:
            solved = _solve(burst, frames, exposures, n_fit, fit, solver, cfg, names, S_motion, progress, held_out)
        solver, fit, k, confidence = solved.solver, solved.fit, solved.k, solved.confidence
        motion, in_frame, excluded, moving = fit.motion, fit.in_frame, fit.excluded, fit.moving
        plane_reports, holdout_report = solved.reports, solved.holdout
        if holdout and checking.short_mosaic(burst, n_fit):  # nor is its pixel FPN measured (a 320x240 raw12
            # DNG burst of 5 frames, seed 2: 1.40 % for a true 1.00 %)
            plane_reports = {name: dataclasses.replace(p, input_fpn_percent=None) for name, p in plane_reports.items()}
        plane_reports, dark_warnings = darkness.reported(burst, fit_frames, solver.floors, plane_reports,
                                                         cfg.solver.min_snr)
        warnings.extend(dark_warnings)
        timings["solve_s"] = chosen_s + sum(t.solve_s for t in tried or [solved])
        if holdout:
            timings["holdout_s"] = sum(t.holdout_s for t in tried or [solved])
            if solved.failed:
                warnings.append(checking.rejection(holdout_report, solved.failed, burst, n_fit))
    if codes is not None:  # no gain is known there; corrected frames repair them (output.repair)
        defective.add_hot(codes, solved.hot)  # those the scene model shows
        defective.leave_out(k, confidence, codes, burst.cfa, burst.channels)
    in_frame_pixels = np.stack([S_motion @ H @ np.linalg.inv(S_motion) for H in motion.homographies])
    solving.lost_band_counted(burst, frames, in_frame_pixels, slice(0, n_fit), k, confidence, plane_reports, solver)
    sigma = sigma_from_confidence(confidence)
    # only the accurate and scene solvers' confidence is a calibrated standard error
    calibrated = (confidence > 0).any() and all(p.method in CALIBRATED_METHODS for p in plane_reports.values())
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
        solver=choice,
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
        defects=None if codes is None else Defects(**defective.counts(codes), dark_frame=burst.dark_hot is not None),
        planes=plane_reports,
        config=config_dict(cfg),
        timings={"read_s": burst.read_s, **timings},
        versions=_versions(),
        warnings=tuple(warnings),
    )
    return Estimate(k.astype(np.float32), confidence.astype(np.float32), report, codes)


@dataclasses.dataclass(frozen=True)
class _Fit:
    """The motion a solve runs on (a refine round replaces it): the warps, in frame pixels, and
    the readings masked as moving with the share of the pixels they are."""

    motion: object
    in_frame: object
    excluded: np.ndarray | None
    moving: list[float] | None


@dataclasses.dataclass(frozen=True)
class _Solved:
    """One solver's map, its planes' reports, the motion it ended on, and its hold-out check
    (None without one) with the grids that check rejected (written k = 1)."""

    solver: solving.Solver
    k: np.ndarray
    confidence: np.ndarray
    reports: dict
    fit: _Fit
    holdout: object
    failed: list
    solve_s: float
    holdout_s: float
    hot: np.ndarray  # photosites the scene model shows hot (solving.solve_planes)


def _solve(burst, frames, exposures, n_fit: int, fit: _Fit, solver, cfg: Config, names, S_motion, progress,
           held_out: str | None) -> _Solved:
    """k and confidence from the first ``n_fit`` frames (with ``cfg.motion.refine_rounds`` rounds of
    motion estimated again on the corrected frames), checked on the frame named ``held_out`` (None:
    unchecked); the rejected grids written as k = 1, confidence 0."""
    t0 = time.perf_counter()
    motion, in_frame, excluded, moving = fit.motion, fit.in_frame, fit.excluded, fit.moving
    planes = solving.solve_planes(burst, frames, excluded, exposures, slice(0, n_fit), in_frame, solver, progress,
                                  split=cfg.motion.refine_rounds == 0)
    for round_ in range(1, cfg.motion.refine_rounds + 1):
        corrected, _ = motion_frames(frames * (planes.k / np.float32(power_of_two_scale(frames[0])))[None], burst.cfa)
        # the model is chosen again: on frames without their gain pattern the choice can change (a forced
        # "layers" would also lose the base model auto chose for it)
        ignore = reference_cells(excluded, corrected.shape[1:], burst.cfa)  # no corner on what the round masked
        motion = estimate_motion(corrected, model=cfg.motion.model, ignore=ignore, exposures=exposures)
        if cfg.motion.model != "auto":
            _check_misfit(motion, names, S_motion)
        reason = f"{motion.reason}; refined on frames corrected by k (round {round_})"
        motion = dataclasses.replace(motion, reason=reason)
        in_frame = motion.warp.conjugate(np.linalg.inv(S_motion))
        excluded, moving = _moving(frames, corrected, motion.warp, burst.cfa, cfg, exposures)
        del corrected
        planes = solving.solve_planes(burst, frames, excluded, exposures, slice(0, n_fit), in_frame, solver,
                                      progress, split=round_ == cfg.motion.refine_rounds)  # measured on the final fit
    solve_s = time.perf_counter() - t0
    k, confidence, plane_reports = planes.k, planes.confidence, planes.reports
    holdout_report, failed = None, []
    if held_out is not None:
        holdout_report, failed = checking.check(burst, frames, excluded, exposures, n_fit, in_frame, solver,
                                               plane_reports, planes.calibrations, progress, held_out, k, confidence)
        for grid in failed:
            grid.scatter(k, np.ones(grid.shape, np.float32))
            grid.scatter(confidence, np.zeros(grid.shape, np.float32))
    return _Solved(solver, k, confidence, plane_reports, _Fit(motion, in_frame, excluded, moving), holdout_report,
                   failed, solve_s, time.perf_counter() - t0 - solve_s, planes.hot)


def _pixel_fpn(reports: dict) -> float:
    """The median over the planes of the input pixel FPN their reports measured (0 if none did)."""
    measured = [p.input_fpn_percent["pixel"] / 100.0 for p in reports.values() if p.input_fpn_percent]
    return float(np.median(measured)) if measured else 0.0


def _check_misfit(motion, names: list[str], S_motion: np.ndarray) -> None:
    """Refuse a forced motion model that leaves out how the frames move (:data:`MAX_MISFIT_PX`, in
    pixels of the tracked images; ``S_motion`` maps them to frame pixels, for the message)."""
    misfits = [f.misfit_px or 0.0 for f in motion.per_frame]
    worst = int(np.argmax(misfits))
    if misfits[worst] > MAX_MISFIT_PX:
        cell = abs(float(S_motion[0, 0]))  # frame pixels per tracked pixel: 2 for a CFA's 2x2 cells
        unit = "px" if cell == 1 else f"px of the {cell:g}x{cell:g} cells motion is tracked on"
        raise EstimationError(
            f"motion.model {motion.model} leaves out how the frames move: in {names[worst]} it is "
            f"{misfits[worst]:.3f} {unit} (RMS over the frame; at most {MAX_MISFIT_PX} allowed) from the homography "
            "fitted to the same tracked points, so the map would be fitted to misaligned frames; use motion.model "
            "auto or homography")


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


def _versions() -> dict:
    import cv2
    import OpenImageIO
    import rawpy
    import scipy

    return {"gainfpn": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "opencv": cv2.__version__, "openimageio": OpenImageIO.__version__,
            "rawpy": rawpy.__version__}
