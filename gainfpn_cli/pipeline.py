"""Burst + config -> gain map: the only place config sections are unpacked.

``estimate`` runs motion, the solver and the FPN model on every plane of a
burst (one for monochrome frames, R G B for RGB EXR, the four 2x2 positions
of a CFA mosaic, whose motion is estimated once on a grey proxy and mapped
exactly to each plane). ``write_estimate`` stages every output in a temporary
directory and renames it into place only when all are written.
"""

from __future__ import annotations

import dataclasses
import json
import platform
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import __version__
from .accurate import AccurateOptions, power_of_two_scale, sigma_from_confidence, solve_accurate
from .bayer import OFFSETS, green_lattice, grey_proxy, plane_to_mosaic
from .blocks import GainResult, solve_paper
from .config import Config, config_dict, dump_config
from .errors import EstimationError, InputError, TrackingError
from .fpnmodel import select_model
from .io import (ATTR_CFA, ATTR_SATURATION, FileStamp, atomic_output, check_consistent, find_frames,
                 read_exr_planes, read_frame, stamp, write_exr, write_text)
from .outdir import OutputPlan, prepare, staged
from .preview import write_preview
from .metrics import mse, residual_fpn_percent
from .exposure import relative_exposures, rough_exposures, significant
from .motion import estimate_motion, moving_masks
from .solver import SolveOptions
from .warp import positions as warp_positions
from .warp import sample, valid_samples

#: Fewest frames a burst needs; the hold-out check needs one more, since a
#: fit on 2 frames is never trusted. Measured: 2 frames, residual FPN 7.5-11 %
#: from 5 % (64x80); 3 frames unchecked, 1.1-1.3 % on 64x80 but 2.9 % and
#: an MSE ratio of 0.9x on 640x480 (bench, frames group).
MIN_FRAMES = 3
#: Fewest pixels per side of the images motion is tracked on (measured: 48 px
#: frames lose frames to too few inliers; 64 px work).
MIN_TRACK_SIDE = 64
#: Fraction of the reference's pixels at or below black above which the
#: estimate warns that the burst is read-noise limited. Measured (64x80x6
#: bursts, 5 % FPN, frames dark all over): 2-6 % of pixels at 0 (median
#: 2.4-3.7 DN) gave residual FPN 5.4-7.7 %, worse than none, with the
#: hold-out check passing; 0.5 % (7 DN) gave 3.6-4.1 %. A scene with deep
#: shadows also crosses it while its bright parts are fine, so it is a
#: warning, not an error.
MAX_DARK_FRACTION = 0.01

#: progress(stage, total) -> update(n): the CLI's tqdm, or nothing
Progress = Callable[[str, int], Callable[[int], None]]


@dataclass(frozen=True)
class LoadedBurst:
    paths: list[Path]
    frames: np.ndarray  # (F, H, W, C) float32, DN after black level (and dark frame)
    cfa: str | None
    channels: tuple[str, ...]
    saturation: float | None
    reference: int
    stamps: tuple[FileStamp, ...] = ()  # each frame file's path, size, time and digest
    dark: FileStamp | None = None  # the master dark frame subtracted, if any
    read_s: float = 0.0  # time taken to read the frames
    white: float | None = None  # the files' white level in DN (black level included), when they state one


@dataclass(frozen=True)
class Estimate:
    k: np.ndarray  # (H, W, C) float32
    confidence: np.ndarray  # (H, W, C) float32
    report: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)


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


@dataclass(frozen=True)
class _Grid:
    """Photosites solved together: ``gather`` takes them out of an ``(..., H, W, C)``
    array as ``(..., h, w)`` grids, ``scatter(dst, grids)`` puts values back, and ``S``
    maps grid pixels to frame pixels. ``positions`` names the planes it covers."""

    name: str
    gather: Callable
    scatter: Callable
    S: np.ndarray
    positions: tuple[str, ...]


def _positions(burst: LoadedBurst):
    """(name, pick, S) per plane the gauge and the FPN model work on: the 2x2 positions of a
    CFA mosaic, or the channels; ``pick`` views the plane in an ``(..., H, W, C)`` array,
    ``S`` maps plane pixels to frame pixels."""
    if burst.cfa:
        for (dy, dx), colour in zip(OFFSETS, burst.cfa):
            yield f"{colour}@{dy}{dx}", (lambda a, dy=dy, dx=dx: a[..., dy::2, dx::2, 0]), plane_to_mosaic((dy, dx))
    else:
        for c, name in enumerate(burst.channels):
            yield name, (lambda a, c=c: a[..., c]), np.eye(3)


def _grids(burst: LoadedBurst, shape: tuple[int, int], method: str):
    """The grids the solver runs on: each plane, except that the accurate solver takes the
    two greens of a CFA together on their rotated lattice (:class:`bayer.GreenLattice`)."""
    lattice = green_lattice(burst.cfa, shape) if burst.cfa and method == "accurate" else None
    if lattice is not None:
        greens = tuple(f"G@{dy}{dx}" for (dy, dx), colour in zip(OFFSETS, burst.cfa) if colour == "G")

        def scatter(dst, grids):
            lattice.scatter(dst[..., 0], grids)

        yield _Grid("G", lambda a: lattice.gather(a[..., 0]), scatter, lattice.S, greens)
    for name, pick, S in _positions(burst):
        if lattice is not None and name.startswith("G@"):
            continue

        def scatter(dst, grids, pick=pick):
            pick(dst)[...] = grids

        yield _Grid(name, pick, scatter, S, (name,))


def _motion_images(frames: np.ndarray, cfa: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Grey images motion is estimated on, and S mapping their pixels to frame pixels."""
    if cfa:
        return np.stack([grey_proxy(f[..., 0]) for f in frames]), plane_to_mosaic((0.5, 0.5))
    if frames.shape[3] == 1:
        return frames[..., 0], np.eye(3)  # a view: no copy of a monochrome stack
    return frames.mean(axis=3), np.eye(3)


def estimate(burst: LoadedBurst, cfg: Config, *, progress: Progress | None = None) -> Estimate:
    """Motion, solve and FPN model for every plane; the hold-out check; a report.

    BLAS and OpenMP run single-threaded meanwhile (:func:`parallel.single_threaded_math`),
    whoever calls, so every caller gets the command's speed and bit-identical results."""
    from .parallel import single_threaded_math

    with single_threaded_math():
        return _estimate(burst, cfg, progress)


def _estimate(burst: LoadedBurst, cfg: Config, progress: Progress | None) -> Estimate:
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
    motion_images, S_motion = _motion_images(frames, burst.cfa)
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
    fit = in_frame.select(range(n_fit))
    k, confidence, plane_reports = _solve_planes(burst, frames, excluded, exposures, n_fit, fit, cfg, progress)
    for round_ in range(1, cfg.motion.refine_rounds + 1):
        corrected, _ = _motion_images(frames * (k / np.float32(power_of_two_scale(frames[0])))[None], burst.cfa)
        # the model is chosen again: on frames without their gain pattern the choice can change (a forced
        # "layers" would also lose the base model auto chose for it)
        ignore = _reference_moving(excluded, corrected.shape[1:], burst.cfa)  # no corner on what the round masked
        motion = estimate_motion(corrected, model=cfg.motion.model, ignore=ignore, exposures=exposures)
        reason = f"{motion.reason}; refined on frames corrected by k (round {round_})"
        motion = dataclasses.replace(motion, reason=reason)
        in_frame = motion.warp.conjugate(np.linalg.inv(S_motion))
        excluded, moving = _moving(frames, corrected, motion.warp, burst.cfa, cfg, exposures)
        del corrected
        fit = in_frame.select(range(n_fit))
        k, confidence, plane_reports = _solve_planes(burst, frames, excluded, exposures, n_fit, fit, cfg, progress)
    timings["solve_s"] = time.perf_counter() - t0

    holdout_report = None
    if holdout:
        ratio = _holdout_ratio(burst, frames, excluded, exposures, in_frame, k, cfg.solver.method)
        holdout_report = {"frame": burst.paths[order[-1]].name, "residual_ratio": ratio, "passed": ratio < 1.0}
        timings["holdout_s"] = time.perf_counter() - t0 - timings["solve_s"]
        if ratio >= 1.0:
            warnings.append(f"the estimate does not reduce the brightness-constancy residual on the held-out frame "
                            f"(ratio {ratio:.3f}); writing k = 1 (no correction)")
            k = np.ones_like(k)
            confidence = np.zeros_like(confidence)
    sigma = sigma_from_confidence(confidence)
    # only the accurate solver's confidence is a calibrated standard error
    calibrated = (confidence > 0).any() and all(p["method"] == "accurate" for p in plane_reports.values())
    report = {
        "version": __version__,
        "status": status(holdout_report),
        # the sensor's gain nonuniformity as estimated (EMVA 1288 parts), and what correction leaves
        "prnu_percent": prnu_percent(plane_reports),
        "predicted_residual_percent": float(100 * np.median(sigma[confidence > 0])) if calibrated else None,
        "holdout": holdout_report,
        "estimated_percent": float(100 * (confidence > 0).mean()),
        "inputs": [s.to_json() for s in burst.stamps] or [str(p.absolute()) for p in burst.paths],
        "dark": None if burst.dark is None else burst.dark.to_json(),
        "white_level_dn": burst.white,
        "reference": burst.paths[burst.reference].name,
        "motion": {
            "model": motion.model,
            "reason": motion.reason,
            # the layers model: each layer besides the dominant one, its model and tracked points
            "layers": motion.layers,
            "frames": [{"frame": burst.paths[order[i + 1]].name, **{k_: v for k_, v in f.items() if k_ != "gric"},
                        "homography": _frame_homography(motion.homographies[i + 1], S_motion)}
                       for i, f in enumerate(motion.per_frame)],
            "refine_rounds": cfg.motion.refine_rounds,
            # per frame, reference first: pixels left out because they do not follow the global motion
            "moving_percent": moving,
        },
        # per frame, reference first: its exposure relative to the reference's; "relative" (the measured
        # one where it differs from 1 significantly) is divided out
        "exposure": exposure_report,
        "planes": plane_reports,
        "config": config_dict(cfg),
        "timings": {"read_s": burst.read_s, **timings},
        "versions": _versions(),
        "warnings": warnings,
    }
    return Estimate(k.astype(np.float32), confidence.astype(np.float32), report, warnings)


def status(holdout: dict | None) -> str:
    """``accepted`` (the hold-out frame confirms the map), ``rejected`` (it did not: k = 1 was
    written) or ``unchecked`` (no frame held out)."""
    if holdout is None:
        return "unchecked"
    return "accepted" if holdout["passed"] else "rejected"


def prnu_percent(plane_reports: dict) -> dict:
    """The input gain nonuniformity in EMVA 1288's parts (percent of the mean gain): ``pixel``,
    ``column`` and ``row`` (even/odd rows), their quadrature sum ``total``, per plane and combined
    over the planes (root mean square). From the FPN model's split (the accurate method; the pixel
    part has the estimation noise removed); None for the paper method, which has no split."""
    planes = {name: p["input_fpn_percent"] for name, p in plane_reports.items() if "input_fpn_percent" in p}
    if not planes:
        return {"total": None, "pixel": None, "column": None, "row": None, "planes": {}}

    def with_total(parts: dict) -> dict:
        parts = {part: float(parts[part]) for part in ("pixel", "column", "row")}
        return {"total": float(np.sqrt(sum(v**2 for v in parts.values()))), **parts}

    per_plane = {name: with_total(parts) for name, parts in planes.items()}
    combined = with_total({part: np.sqrt(np.mean([p[part] ** 2 for p in per_plane.values()]))
                           for part in ("pixel", "column", "row")})
    return {**combined, "planes": per_plane}


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


def _frame_homography(H: np.ndarray, S: np.ndarray) -> list:
    """``H_t_ref`` of the motion images in frame pixels (mosaic photosites for RAW), as nested lists."""
    H = np.asarray(S) @ H @ np.linalg.inv(S)
    return (H / H[2, 2]).tolist()


def _reference_moving(excluded: np.ndarray | None, shape: tuple[int, int], cfa: str | None) -> np.ndarray | None:
    """The reference's pixels masked as moving, on the motion images' ``shape`` grid (a CFA's 2x2 cells)."""
    if excluded is None:
        return None
    return excluded[0, ::2, ::2][: shape[0], : shape[1]] if cfa else excluded[0]


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


def _exposures(motion_images, warp, burst, cfg) -> tuple[np.ndarray, dict]:
    """Each frame's exposure relative to the reference (:mod:`exposure`), measured on the motion
    images (a CFA's 2x2 cells: a clipped photosite lowers its cell, the median shrugs a few off)
    and kept where it differs from 1 significantly; all ones with ``input.exposure: fixed``. And
    what the report says of them."""
    if cfg.input.exposure == "fixed":
        return np.ones(len(motion_images)), {"mode": "fixed"}
    measured, errors = relative_exposures(motion_images, warp, saturation=burst.saturation)
    used = significant(measured, errors)
    return used, {"mode": "per-frame", "relative": [round(float(c), 6) for c in used],
                  "measured": [round(float(c), 6) for c in measured],
                  "log_standard_error": [float(e) if np.isfinite(e) else None for e in errors]}


def _solve_planes(burst, frames, excluded, exposures, n_fit, in_frame, cfg, progress):
    """k and confidence of every plane from the first ``n_fit`` frames, with the FPN model and the gauge."""
    s = cfg.solver
    k = np.ones(frames.shape[1:], np.float32)
    confidence = np.zeros(frames.shape[1:], np.float32)
    fit = frames[:n_fit]
    left_out = None if excluded is None else np.broadcast_to(excluded[:n_fit, ..., None], fit.shape)  # every channel
    solved = {}
    for grid in _grids(burst, frames.shape[1:3], s.method):
        result, info = _solve_grid(grid.gather(fit), None if left_out is None else grid.gather(left_out),
                                   in_frame.conjugate(grid.S), burst.saturation, cfg, progress, grid.name,
                                   mosaic=burst.cfa is not None, exposures=exposures[:n_fit])
        grid.scatter(k, result.k)
        grid.scatter(confidence, result.confidence)
        solved.update({name: {**info, "solved_on": grid.name} for name in grid.positions})
    reports = {}
    for name, pick, _ in _positions(burst):  # the gauge and the FPN model, plane by plane
        info, structured = dict(solved[name]), False
        kp = pick(k)
        if s.method == "accurate":
            model = select_model(kp, pick(confidence), force=None if s.fpn_model == "auto" else s.fpn_model)
            info.update(fpn_model=model.chosen, fpn_model_aic=model.scores, input_fpn_percent=model.split)
            kp, structured = model.k, model.chosen not in ("pixel", "none")
        result = _physical(GainResult(kp, pick(confidence), {}), s.gain_range, structured)
        pick(k)[...] = result.k
        pick(confidence)[...] = result.confidence
        reports[name] = info
    return k, confidence, reports


def _solve_grid(frames, excluded, motion, saturation, cfg, progress, name, mosaic=False,
                exposures=None) -> tuple[GainResult, dict]:
    s = cfg.solver
    update = progress(f"solve {name}", 0) if progress else None
    if s.method == "paper":
        if excluded is not None:  # the published form takes zeroed pixels as missing
            frames = np.where(excluded, np.float32(0), frames)
        if exposures is not None and np.any(exposures != 1.0):  # clipped pixels marked missing before scaling
            if saturation is not None:
                frames = np.where(frames >= saturation, np.float32(0), frames)
            frames = frames / np.asarray(exposures, np.float32)[:, None, None]
        region = (0, 0) + frames.shape[1:]
        positions = np.stack([warp_positions(motion.pair(0, t, region), frames.shape[1:])
                              for t in range(1, len(frames))])
        options = SolveOptions(lam=s.lam, max_condition=s.max_condition, k_range=s.gain_range)
        result = solve_paper(frames, positions, block_size=s.block_size, options=options, saturation=saturation,
                             workers=s.workers, progress=update)
        return result, {"method": "paper", **result.stats}
    options = AccurateOptions(kernel=s.interpolation, anchors=s.anchors, partners=s.partners, rtol=s.rtol,
                              gauge_sigma=s.gauge_sigma, tile=s.tile,
                              robust_rounds=s.robust_rounds, gain_range=s.gain_range,
                              phase_weights=s.phase_weights == "all" or (s.phase_weights == "auto" and mosaic))
    result = solve_accurate(frames, motion, options=options, saturation=saturation, excluded=excluded,
                            exposures=exposures, workers=s.workers, progress=update)
    return result, {"method": "accurate", **result.stats}


def _physical(result: GainResult, gain_range: tuple[float, float], structured: bool = False) -> GainResult:
    """``result`` with every estimated k in ``gain_range`` and the gauge (mean 1 over the
    estimated pixels) kept: a renormalisation can push a k just past a limit, so pixels
    past it are left unestimated (k = 1, confidence 0) until none is. A ``structured``
    map also gives unestimated pixels their column / row gain, renormalised with the rest."""
    k = np.array(result.k, np.float32)
    confidence = np.array(result.confidence, np.float32)
    low, high = gain_range
    while True:  # each round leaves at least one more pixel unestimated
        est = confidence > 0
        outside = est & ((k < low) | (k > high))
        if not outside.any():
            break
        est &= ~outside
        if est.any():
            k[np.ones(k.shape, bool) if structured else est] /= k[est].mean(dtype=np.float64)
        k[outside], confidence[outside] = 1.0, 0.0
    return GainResult(k.astype(np.float32), confidence.astype(np.float32), result.stats)


def _holdout_ratio(burst, frames, excluded, exposures, in_frame, k, method: str) -> float:
    """Brightness-constancy residual of the held-out frame against the reference, with k over without
    (the held-out frame brought to the reference's exposure)."""
    num = den = 0.0
    sat = np.inf if burst.saturation is None else burst.saturation
    scale = np.float32(power_of_two_scale(frames[0]))  # about 1: k times a frame stays far from float32's limits
    for grid in _grids(burst, frames.shape[1:3], method):
        ref, held, kp = grid.gather(frames[0]), grid.gather(frames[-1]), grid.gather(k)
        ref_ok, held_ok = (ref > 0) & (ref < sat), (held > 0) & (held < sat)
        if excluded is not None:
            ref_ok &= ~grid.gather(np.broadcast_to(excluded[0, ..., None], frames.shape[1:]))
            held_ok &= ~grid.gather(np.broadcast_to(excluded[-1, ..., None], frames.shape[1:]))
        ref, held = ref / scale, held / (scale * np.float32(exposures[-1]))
        shape = ref.shape
        M = in_frame.conjugate(grid.S).pair(0, len(frames) - 1, (0, 0) + shape)
        valid = valid_samples(held_ok, M, shape) & ref_ok
        with_k = kp * ref - sample(kp * held, M, shape)
        without = ref - sample(held, M, shape)
        num += float(np.sum(with_k[valid] ** 2))
        den += float(np.sum(without[valid] ** 2))
    return num / den if den > 0 else 1.0


def _versions() -> dict:
    import cv2
    import OpenImageIO
    import rawpy
    import scipy

    return {"gainfpn": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "opencv": cv2.__version__, "openimageio": OpenImageIO.__version__,
            "rawpy": rawpy.__version__}


# ---------------------------------------------------------------------------
# outputs


def _gain_planes(k: np.ndarray, confidence: np.ndarray, channels: tuple[str, ...], cfa: str | None) -> dict:
    if cfa or len(channels) == 1:
        return {"Y": k[..., 0], "confidence": confidence[..., 0]}
    planes = {}
    for c, name in enumerate(channels):
        planes[name] = k[..., c]
        planes[f"{name}.confidence"] = confidence[..., c]
    return planes


#: What ``estimate`` writes into its output folder (``--overwrite`` replaces these names only).
ESTIMATE_OUTPUTS = ("gain_map.exr", "corrected", "preview.png", "config.used.yaml", "report.json")


def estimate_plan(out_dir: Path, paths, cfg: Config, *, overwrite: bool = False) -> OutputPlan:
    """Check ``out_dir`` for an estimate of the frames ``paths`` before any work (:func:`outdir.prepare`)."""
    _check_unique_stems(list(paths))
    inputs = [*paths, *([cfg.input.dark] if cfg.input.dark else [])]
    return prepare(out_dir, command="estimate", names=ESTIMATE_OUTPUTS, inputs=inputs, overwrite=overwrite)


def write_estimate(result: Estimate, burst: LoadedBurst, cfg: Config, out_dir: Path, *, overwrite: bool = False,
                   progress: Progress | None = None) -> OutputPlan:
    """gain_map.exr, corrected/*.exr, report.json, config.used.yaml and preview.png, all or nothing.

    Only these names are replaced in ``out_dir`` (and an earlier evaluation of them removed); the
    returned plan lists what else the folder holds, untouched."""
    plan = estimate_plan(out_dir, burst.paths, cfg, overwrite=overwrite)
    t0 = time.perf_counter()
    config_text = dump_config(cfg)
    metadata = {"gainfpn:version": __version__, "gainfpn:config": config_text,
                "gainfpn:inputs": json.dumps([str(p.absolute()) for p in burst.paths]),
                "gainfpn:motion_model": result.report["motion"]["model"]}
    if burst.dark is not None:  # `apply` subtracts the same dark frame before k
        metadata[ATTR_DARK] = json.dumps({"path": burst.dark.path, "sha256": burst.dark.sha256})
    if burst.cfa:
        metadata[ATTR_CFA] = burst.cfa
    with staged(plan) as tmp:
        write_exr(tmp / "gain_map.exr", _gain_planes(result.k, result.confidence, burst.channels, burst.cfa),
                  metadata=metadata, compression=cfg.output.compression)
        if cfg.output.corrected:
            (tmp / "corrected").mkdir()
            update = progress("write", len(burst.paths)) if progress else None
            _write_corrected(lambda i: (burst.paths[i], burst.frames[i]), len(burst.paths), result.k,
                             tmp / "corrected", cfa=burst.cfa, channels=burst.channels, saturation=burst.saturation,
                             compression=cfg.output.compression, update=update)
        if cfg.output.preview:
            write_preview(tmp / "preview.png", result.k, result.confidence, report=result.report,
                          name=burst_name(burst.paths), cfa=burst.cfa, channels=burst.channels)
        write_text(tmp / "config.used.yaml", config_text)
        timings = result.report["timings"]
        timings["write_s"] = time.perf_counter() - t0
        timings["total_s"] = sum(v for key, v in timings.items() if key != "total_s")
        write_text(tmp / "report.json", json.dumps(result.report, indent=1))
    return plan


#: Header attribute of a gain map estimated on dark-subtracted frames: that dark frame's path and digest.
ATTR_DARK = "gainfpn:dark"


def _write_corrected(frame: Callable[[int], tuple[Path, np.ndarray]], count: int, k: np.ndarray, folder: Path, *,
                     cfa: str | None, channels: tuple[str, ...], saturation: float | None, compression: str,
                     update=None) -> None:
    """``folder/<stem>.exr`` = ``k`` times each frame ``frame(i) -> (path, DN)`` for ``i < count``:
    the one writer of corrected frames, for ``estimate`` and ``apply`` alike."""
    names = ("Y",) if cfa or len(channels) == 1 else channels
    metadata: dict = {"gainfpn:version": __version__}
    if cfa:
        metadata[ATTR_CFA] = cfa
    if saturation is not None:
        metadata[ATTR_SATURATION] = float(saturation)

    def write(i: int) -> None:
        path, data = frame(i)
        corrected = data * k
        _check_finite(corrected, path)
        write_exr(folder / f"{path.stem}.exr", {n: corrected[..., c] for c, n in enumerate(names)},
                  metadata=metadata, compression=compression)

    for i in range(0, count, 2):
        _in_pair(write, i, i + 1 < count)
        if update:
            update(min(2, count - i))


def burst_name(paths: list[Path]) -> str:
    """What the preview's title calls a burst: its folder, or its first and last frames."""
    folders = {p.absolute().parent for p in paths}
    if len(folders) == 1:
        return f"{folders.pop().name}/"
    return f"{paths[0].name} ... {paths[-1].name}"


def _check_unique_stems(paths: list[Path]) -> None:
    """Corrected frames are named by their input's stem: two inputs must not share one."""
    seen: dict[str, Path] = {}
    for path in paths:
        if path.stem in seen:
            raise InputError(f"{path}: has the same name as {seen[path.stem]}; their corrected frames would both "
                             f"be {path.stem}.exr")
        seen[path.stem] = path


#: On an error or an interrupt, how long (s) the other frame's write may take to finish (a 12 MP
#: frame takes ~0.1 s) before the staging directory is removed under it.
WRITE_GRACE_S = 5.0


def _in_pair(fn: Callable[[int], None], i: int, both: bool) -> None:
    """``fn(i)`` here and, if ``both``, ``fn(i + 1)`` at the same time on a daemon thread.

    OpenImageIO releases the GIL while it encodes and writes, so two frames at
    a time take half the time (12 MP x 8 uncompressed: 0.94 -> 0.49 s). The
    thread is a daemon: an interrupt here waits for it at most WRITE_GRACE_S
    (then the staging directory it writes into is removed).
    """
    failed: list[BaseException] = []

    def other() -> None:
        try:
            fn(i + 1)
        except BaseException as exc:  # raised here, in the caller's thread
            failed.append(exc)

    thread = threading.Thread(target=other, daemon=True) if both else None
    if thread:
        thread.start()
    try:
        fn(i)
    except BaseException:  # give the other write a moment to finish before its folder is removed
        if thread:
            thread.join(timeout=WRITE_GRACE_S)
        raise
    if thread:
        thread.join()
    if failed:
        raise failed[0]


def _check_finite(corrected: np.ndarray, path: Path) -> None:
    if not np.isfinite(corrected).all():
        raise EstimationError(f"{path}: the corrected frame exceeds the float32 range (inputs near 3.4e38); "
                              "scale the input down")


# ---------------------------------------------------------------------------
# apply and evaluate


def read_gain_map(path: Path) -> tuple[np.ndarray, dict]:
    """k as ``(H, W, C)`` and the map's attributes."""
    planes, attrs = read_exr_planes(path)
    if "Y" in planes:
        return planes["Y"][..., None], attrs
    names = [n for n in ("R", "G", "B") if n in planes]
    if not names:
        raise InputError(f"{path}: not a gainfpn gain map (no Y or R G B channel)")
    return np.stack([planes[n] for n in names], axis=-1), attrs


def apply_dark(attrs: dict, dark: Path | None, gain_map: Path) -> Path | None:
    """The dark frame to subtract before ``k``: the one the map was estimated with (its header
    records path and digest), found at its recorded path or given as ``dark``; a different
    dark frame, or one for a map estimated without, is refused."""
    recorded = json.loads(attrs[ATTR_DARK]) if ATTR_DARK in attrs else None
    if recorded is None:
        if dark is not None:
            raise InputError(f"{gain_map}: was estimated without a dark frame, so --dark {dark} would correct "
                             "differently from the estimate; subtract it from the inputs first, or estimate with it")
        return None
    if dark is None:
        dark = Path(recorded["path"])
        if not dark.is_file():
            raise InputError(f"{gain_map}: was estimated with the dark frame {recorded['path']} subtracted, which is "
                             "gone; pass it with --dark")
    if stamp(dark).sha256 != recorded["sha256"]:
        raise InputError(f"{dark}: is not the dark frame the gain map was estimated with ({recorded['path']}, "
                         f"sha256 {recorded['sha256'][:12]}...)")
    return dark


def apply_plan(gain_map: Path, paths: list[Path], out_dir: Path, *, dark: Path | None = None,
               overwrite: bool = False) -> OutputPlan:
    """Check ``out_dir`` for the corrected frames of ``paths`` before any work (:func:`outdir.prepare`)."""
    _check_unique_stems(paths)
    return prepare(out_dir, command="apply", names=[f"{p.stem}.exr" for p in paths],
                   inputs=[*paths, gain_map, *([dark] if dark else [])], overwrite=overwrite)


def apply_gain_map(gain_map: Path, inputs, out_dir: Path, *, dark: Path | None = None, overwrite: bool = False,
                   progress: Progress | None = None) -> tuple[list[Path], OutputPlan]:
    """Correct other captures with a stored map, exactly as ``estimate`` corrects its own frames
    (the map's dark frame subtracted first); return the frames written and the output plan."""
    k, attrs = read_gain_map(gain_map)
    dark = apply_dark(attrs, dark, gain_map)
    paths = find_frames(inputs)
    plan = apply_plan(gain_map, paths, out_dir, dark=dark, overwrite=overwrite)
    dark_data = None if dark is None else read_frame(dark).data
    if dark_data is not None and dark_data.shape != k.shape:
        raise InputError(f"{dark}: dark frame is {dark_data.shape[1]}x{dark_data.shape[0]}, the gain map "
                         f"{k.shape[1]}x{k.shape[0]}")
    update = progress("apply", len(paths)) if progress else None
    first = read_frame(paths[0])

    def frame(i: int) -> tuple[Path, np.ndarray]:
        read = first if i == 0 else read_frame(paths[i])
        check_consistent([first.info, read.info])
        data = read.data
        if data.shape != k.shape:
            raise InputError(f"{read.info.path}: frame is {data.shape[1]}x{data.shape[0]} with {data.shape[2]} "
                             f"channel(s); the gain map is {k.shape[1]}x{k.shape[0]} with {k.shape[2]}")
        if (read.info.cfa or None) != (attrs.get(ATTR_CFA) or None):
            raise InputError(f"{read.info.path}: CFA layout {read.info.cfa or 'none'} does not match the gain map's "
                             f"{attrs.get(ATTR_CFA) or 'none'}")
        return read.info.path, data if dark_data is None else data - dark_data

    with staged(plan) as tmp:
        _write_corrected(frame, len(paths), k, tmp, cfa=first.info.cfa, channels=first.info.channels,
                         saturation=first.info.saturation, compression="zip", update=update)
    return [out_dir / f"{p.stem}.exr" for p in paths], plan


def evaluate(out_dir: Path, sim_dir: Path) -> dict:
    """Residual gain FPN and the paper's MSE before/after, against a simulation's truth.

    Refuses a truth that is not this estimate's: another size, CFA layout or white level
    (bit depth), or frames whose digests differ from those the estimate recorded."""
    from .truth import load_truth, residual_bound_percent

    k, attrs = read_gain_map(out_dir / "gain_map.exr")
    planes, _ = read_exr_planes(out_dir / "gain_map.exr")
    confidence = planes.get("confidence", np.ones(k.shape[:2], np.float32))
    report = _read_report(out_dir)
    truth = load_truth(sim_dir)
    sim_paths = find_frames([sim_dir])
    first = read_frame(sim_paths[0])
    _check_truth(report, attrs, k, truth, first, sim_paths, out_dir, sim_dir)
    est = confidence > 0
    if not est.any():
        raise EstimationError(f"{out_dir}: the gain map has no estimated pixel")
    result = scores(k[..., 0], est, first.data[..., 0], truth)
    n_fit = len(report["inputs"]) - (1 if report.get("holdout") else 0)  # one frame is held out to check k
    bound = residual_bound_percent(truth, est, n_fit)
    return {**result, "residual_bound_percent": bound, "bound_frames": n_fit}


def _read_report(out_dir: Path) -> dict:
    path = out_dir / "report.json"
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
        report["inputs"][0]["sha256"]
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc}); is {out_dir} a folder written by "
                         "`gainfpn estimate`?") from None
    except (ValueError, KeyError, TypeError, IndexError):
        raise InputError(f"{path}: not a report of this gainfpn version (no input digests); estimate again") from None
    return report


def _check_truth(report, attrs, k, truth, first, sim_paths, out_dir: Path, sim_dir: Path) -> None:
    """Raise :class:`InputError` unless ``sim_dir`` holds the burst the estimate in ``out_dir`` was made from."""
    h, w = truth.gain.shape
    if (h, w) != k.shape[:2]:
        raise InputError(f"{sim_dir}: truth is {w}x{h}, the gain map {k.shape[1]}x{k.shape[0]}: not this estimate's "
                         "simulation")
    sim_cfa, est_cfa = first.info.cfa or "none", attrs.get(ATTR_CFA) or "none"
    if sim_cfa != est_cfa:
        raise InputError(f"{sim_dir}: CFA layout {sim_cfa} differs from the estimate's ({est_cfa}): not this "
                         "estimate's simulation")
    sim_white, est_white = first.info.layout()[4], report.get("white_level_dn")
    if sim_white != est_white:
        raise InputError(f"{sim_dir}: white level {_dn(sim_white)} differs from the estimate's frames' "
                         f"({_dn(est_white)}): another bit depth, not this estimate's simulation")
    recorded = {Path(i["path"]).name: i["sha256"] for i in report["inputs"]}
    for path in sim_paths:
        if path.name in recorded and stamp(path).sha256 != recorded.pop(path.name):
            raise InputError(f"{path}: differs from the frame {path.name} the estimate in {out_dir} was made from "
                             "(another simulation, or frames made again)")
    if recorded:
        raise InputError(f"{sim_dir}: has no frame {sorted(recorded)[0]}, which the estimate in {out_dir} was made "
                         "from: not this estimate's simulation")


def _dn(value) -> str:
    return "not stated" if value is None else f"{value:g} DN"


def scores(k: np.ndarray, est: np.ndarray, frame0: np.ndarray, truth) -> dict:
    """Residual gain FPN and the paper's MSE of frame 0 before/after ``k``, over the pixels ``est``."""
    return {
        "estimated_percent": 100.0 * float(est.mean()),
        "input_fpn_percent": residual_fpn_percent(np.ones_like(k), truth.gain, est),
        "residual_fpn_percent": residual_fpn_percent(k, truth.gain, est),
        "mse_before": mse(frame0, truth.ideal, est),
        "mse_after": mse(k * frame0, truth.ideal, est),
        "mse_floor": mse(frame0 / truth.gain, truth.ideal, est),
    }


def simulate_to(out_dir: Path, *, fmt: str, overwrite: bool = False, scene: str | Path = "procedural",
                parameters: dict | None = None, **burst_options) -> tuple[list[Path], OutputPlan]:
    """Simulate a burst (see :func:`simulate.simulate_burst`) and save it, all or nothing; return the
    frames written and the output plan.

    ``scene`` is a built-in scene's name or the path of an image.
    """
    from .io import read_scene
    from .simulate import simulate_burst
    from .truth import check_format, save_burst

    check_format(burst_options["sensor"], fmt)
    names = [f"frame_{t:03d}.{fmt}" for t in range(burst_options["n_frames"])] + ["truth"]
    plan = prepare(out_dir, command="simulate", names=names, inputs=[scene] if isinstance(scene, Path) else [],
                   overwrite=overwrite)
    if isinstance(scene, Path):
        scene = read_scene(scene)
    burst = simulate_burst(scene=scene, **burst_options)
    with staged(plan) as tmp:
        paths = save_burst(burst, tmp, fmt=fmt, parameters=parameters)
    return [out_dir / p.relative_to(tmp) for p in paths], plan
