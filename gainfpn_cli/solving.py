"""Every plane of a burst solved by the solver the config names (:mod:`choosing` resolves ``auto``):
the FPN model and its calibration on two halves of the frames, the hot photosites the scene model
shows left out, and the regions the hold-out check (:mod:`checking`) fits again.

:mod:`pipeline` runs motion and hands the frames, the masks and the warps here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .burst import LoadedBurst
from .darkness import noise_bounded, too_dark
from .defective import offset_shown
from .errors import EstimationError
from .geometry.planes import plane_views, solve_grids
from .geometry.resample import positions as warp_positions
from .geometry.resample import window_sum
from .report import PlaneReport
from .solve import bootstrap
from .solve.accurate import AccurateOptions, comparison_pairs, solve_accurate, solve_accurate_many
from .solve.band import gauge_share, lost_share, shared_band, shifts_at_centre
from .solve.blocks import solve_paper
from .solve.fpnmodel import measure, pooled_priors, select_model
from .solve.halves import Halves
from .solve.kkt import SolveOptions
from .solve.result import (
    GainResult,
    confidence_from_sigma,
    physical,
    sigma_from_confidence,
)
from .solve.scene import SceneOptions, solve_scene_many
from .solve.tiling import each_or_none, usable


@dataclass(frozen=True)
class Solver:
    """The solver section of the config, unpacked once per estimate into the solvers' options."""

    method: str
    paper: SolveOptions
    block_size: int
    accurate: AccurateOptions
    scene: SceneOptions
    fpn_model: str | None  # None: chosen by AIC
    gain_range: tuple[float, float]
    workers: int
    executor: object = None
    floors: dict | None = None  # plane name -> level (DN) at or below which a photosite is not solved
    noise: dict | None = None  # plane name -> solve.noise.NoiseModel of its readings (the defect search's)
    defects: bool = False  # photosites the scene model shows hot are left out (defective.offset_shown)

    @classmethod
    def from_config(cls, s, *, mosaic: bool, defects: bool = False, executor=None) -> "Solver":
        accurate = AccurateOptions(kernel=s.interpolation, anchors=s.anchors, partners=s.partners, rtol=s.rtol,
                                   gauge_sigma=s.gauge_sigma, tile=s.tile, robust_rounds=s.robust_rounds,
                                   gain_range=s.gain_range,
                                   phase_weights=s.phase_weights == "all" or (s.phase_weights == "auto" and mosaic))
        scene = SceneOptions(scale=s.scene_scale, steps=s.scene_steps, gauge_sigma=s.scene_gauge_sigma,
                             gain_range=s.gain_range)
        return cls(s.method, SolveOptions(lam=s.lam, max_condition=s.max_condition, k_range=s.gain_range),
                   s.block_size, accurate, scene, None if s.fpn_model == "auto" else s.fpn_model, s.gain_range,
                   s.workers, executor, defects=defects)

    @property
    def calibrated(self) -> bool:
        """Whether the solver's confidence is a predicted standard error (so that the FPN model, the
        halves' calibration and the hold-out's disagreement can use it)."""
        return self.method in CALIBRATED_METHODS


#: The solvers whose confidence is ``1 / (1 + (sigma_k / 1 %)^2)`` with a predicted sigma_k.
CALIBRATED_METHODS = ("accurate", "scene")


def grids_of(burst: LoadedBurst, frames: np.ndarray, method: str) -> list:
    """The grids the solver runs on (the accurate solver takes a CFA's two greens together)."""
    return list(solve_grids(burst.cfa, burst.channels, frames.shape[1:3], greens_together=method == "accurate"))


def lost_band_counted(burst: LoadedBurst, frames: np.ndarray, homographies: np.ndarray, used: slice, k: np.ndarray,
                      confidence: np.ndarray, reports: dict, solver: Solver) -> None:
    """The written ``sigma_k`` (in ``confidence``, in place) of every plane with a pixel FPN model, with
    the band of its gains the solver never estimates added: ``s^2`` (the plane's measured pixel FPN
    prior) times the share a white pattern loses (:mod:`solve.band`; 0.0034 on a 240x320 8-bit burst
    of 3 px shake, so 0.085 %^2 at 5 % FPN, as large as ``sigma_k^2`` of its most precise pixels).
    Every fit of the burst loses it alike, so halves of the frames cannot measure it (docs/method.md
    section 11). The scene solver, which fits no halves, also gets the error its pixels share as
    ``k`` (the written map) shows it (:func:`solve.band.shared_band`). ``homographies`` are the
    frames' ``H_t_ref`` in frame pixels (the reference first), ``used`` the fitted ones."""
    for grid in grids_of(burst, frames, solver.method):
        methods = {reports[name].method for name in grid.positions if name in reports}
        if methods == {"accurate"}:
            fitted = homographies[used]
            share = lost_share(shifts_at_centre(fitted, grid.S, grid.shape),
                               comparison_pairs(len(fitted), solver.accurate), solver.accurate.gauge_sigma,
                               solver.accurate.mu)
        elif methods == {"scene"}:
            share = gauge_share(solver.scene.gauge_sigma)
        else:
            continue
        for name, pick, _ in plane_views(burst.cfa, burst.channels):
            report = reports.get(name)
            if name not in grid.positions or report is None or report.fpn_model not in ("pixel", "none") \
                    or not report.input_fpn_percent:
                continue
            fpn = report.input_fpn_percent["pixel"] / 100.0
            plane = pick(confidence)  # float32: sigma_k^2 of 1e-8 and more, the band's ~1e-5
            sigma = sigma_from_confidence(plane)
            band = np.float32(fpn**2 * share)
            if methods == {"scene"}:
                band = band + shared_band(pick(k), sigma, plane > 0, fpn).astype(np.float32)
            if np.any(band > 0):
                plane[...] = np.where(plane > 0, confidence_from_sigma(np.sqrt(sigma**2 + band)), 0)


@dataclass(frozen=True)
class Planes:
    """Every plane's k and confidence (frame-shaped) from :func:`solve_planes`, each plane's report and
    calibration (plane name -> :class:`solve.halves.Calibration` or None), and the photosites the
    scene model shows hot (``Solver.defects``; k = 1, confidence 0 there)."""

    k: np.ndarray
    confidence: np.ndarray
    reports: dict
    calibrations: dict
    hot: np.ndarray


def solve_planes(burst, frames, excluded, exposures, used: slice, in_frame, solver: Solver, progress, *,
                  regions: dict | None = None, models: dict | None = None, split: bool = False,
                  calibrations: dict | None = None) -> Planes:
    """k and confidence of every plane from the frames ``used``, with the FPN model and the gauge, and
    what goes with them (:class:`Planes`).

    ``regions`` (grid name -> list of (rows, columns) slices) solves only there, and only the grids it names
    (k = 1 and confidence 0 elsewhere); ``models`` (plane name -> FPN model) forces each plane's model;
    ``split`` measures the accurate solver's sigma_k and pixel FPN of each plane with two more fits, on
    the even and the odd frames of ``used`` (on :func:`measured_regions`, and with
    :data:`MIN_SPLIT_FRAMES` or more; with fewer, its sigma_k on the burst the scene model predicts:
    :func:`bootstrapped`, which also sets the least the halves' factors are outside a CFA mosaic; the
    scene solver's sigma_k is measured by its noise probe, and halves of a burst are too few frames
    for its latent scene), and ``calibrations`` (plane name -> Calibration) gives them as measured
    before."""
    k, confidence, solved, hot = solve_raw(burst, frames, excluded, exposures, used, in_frame, solver, progress,
                                           regions=regions)
    if solver.method == "accurate":  # the scene solver counts readings at black itself (docs/method.md 8b)
        noise_bounded(burst, frames[used], confidence, solver.noise)
    halves = None
    if split and solver.method == "accurate" and len(range(len(frames))[used]) >= MIN_SPLIT_FRAMES:
        middle = measured_regions(burst, frames, solver)
        halves = [half[:2] for half in solve_raws(burst, frames, excluded, exposures,
                                                   [slice(used.start + offset, used.stop, 2) for offset in (0, 1)],
                                                   in_frame, solver, progress, regions=middle)]
    elif split and solver.method == "accurate" and calibrations is None:
        calibrations = bootstrapped(burst, frames, excluded, exposures, used, in_frame, solver, progress, k,
                                    confidence)
    measures = {}
    if halves is not None and calibrations is None and solver.calibrated:
        measures = {name: measure(pick(k), pick(confidence),
                                  Halves(*(pick(m) for half in halves for m in half), not burst.cfa))
                    for name, pick, _ in plane_views(burst.cfa, burst.channels) if name in solved}
        if burst.cfa:  # a mosaic's priors, pooled
            pooled = pooled_priors({name: m.calibration for name, m in measures.items()})
            measures = {name: dataclasses.replace(m, calibration=pooled[name]) for name, m in measures.items()}
        else:  # the error both halves make alike, as the burst the scene model predicts shows it
            floors = bootstrapped(burst, frames, excluded, exposures, used, in_frame, solver, progress, k, confidence)
            combined = bootstrap.raised if hausman_holds(solver.accurate) else bootstrap.instead
            measures = {name: dataclasses.replace(m, calibration=combined(m.calibration, floors.get(name)))
                        for name, m in measures.items()}
    reports, calibrated = {}, {}
    for name, pick, _ in plane_views(burst.cfa, burst.channels):  # the gauge and the FPN model, plane by plane
        if name not in solved:  # its grid has no region: k = 1, confidence 0
            continue
        report, structured, calibration = solved[name], False, None
        kp = pick(k)
        if solver.calibrated:
            plane_halves = None if halves is None else \
                Halves(*(pick(m) for half in halves for m in half), not burst.cfa)
            model = select_model(kp, pick(confidence), force=(models or {}).get(name) or solver.fpn_model,
                                 halves=plane_halves, calibration=(calibrations or {}).get(name),
                                 sigma_calibrated=True, measured=measures.get(name))
            measured = model.sigma is not None and (model.calibration.measured or solver.method == "scene")
            report = dataclasses.replace(report, fpn_model=model.chosen, fpn_base=model.base,
                                         fpn_model_aic=model.scores,
                                         input_fpn_percent=model.split, confidence_calibrated=measured,
                                         column_agreement=(round(float(model.column_agreement), 2)
                                                           if np.isfinite(model.column_agreement) else None))
            kp, structured, calibration = model.k, model.chosen not in ("pixel", "none"), model.calibration
            if model.sigma is not None:
                pick(confidence)[...] = np.where(pick(confidence) > 0, confidence_from_sigma(model.sigma), 0)
        result = physical(GainResult(kp, pick(confidence)), solver.gain_range, structured)
        pick(k)[...] = result.k
        pick(confidence)[...] = result.confidence
        reports[name], calibrated[name] = report, calibration
    return Planes(k, confidence, reports, calibrated, hot)


def hausman_holds(options: AccurateOptions) -> bool:
    """Whether the accurate solver's fit is at least as precise as a fit of either half of its frames, as the
    halves' Hausman difference takes it: not where it compares each frame with fewer than 3 others (each
    half's 4 frames then compare with 2 of their 3) or stops GMRES above 1e-3. On a 640x480x8 procedural
    burst (seed 5) the `fast` preset's halves (2 partners, 3e-2) read factors of 1.43-2.05 over the tenths
    and its written sigma_k 1.1-1.75x k's error; 2 partners at 1e-3 0.67-1.48; 3 at 1e-3 0.72-0.82, raised
    to the model's burst's 1.00-1.10 (docs/limits.md, "Confidence")."""
    return (options.partners == 0 or options.partners >= 3) and options.rtol <= 1e-3


#: Fewest frames :func:`solve_planes` splits into halves to measure sigma_k and the pixel FPN: halves
#: of 2 frames have errors that are far from independent (measured: the pixel FPN 2.5-6 % against a
#: true 1 % at 5 frames), halves of 3 nearly so.
MIN_SPLIT_FRAMES = 6


def bootstrapped(burst, frames, excluded, exposures, used: slice, in_frame, solver: Solver, progress, k,
                 confidence) -> dict:
    """Each plane's :class:`solve.halves.Calibration` of the accurate solver's sigma_k, measured on the
    burst the scene model fitted to the frames ``used`` predicts (:mod:`solve.bootstrap`), on the
    :func:`measured_regions`; ``k`` and ``confidence`` are the fit's, frame-shaped. Planes with too few
    pixels measured, and a CFA mosaic's (whose colour planes' latent scene is still aliased: docs/method.md
    section 8b), are not in it: their sigma_k is the halves' or the solver's own, as every plane's whose
    squares' predicted bursts cannot be fitted again (a square that cannot measures nothing)."""
    if burst.cfa is not None:
        return {}
    regions = measured_regions(burst, frames, solver)
    jobs = _jobs(burst, frames, excluded, exposures, [used], in_frame, solver, regions)
    update = progress("confidence", 0) if progress else None
    # rendered through the warps each frame's mean move over a tile refines (docs/method.md 11): the burst
    # then carries the warps' error as the real one does against those the accurate solver fits it with;
    # the field the scene solver fits (section 8b) would misregister it beyond that. Its exposures are
    # refined, as the real frames' are what they are whatever the exposures the solver is given
    shifted = dataclasses.replace(solver.scene, refine_warps="shift")
    models = [{"frames": f, "motion": m, "saturation": burst.saturation, "excluded": x, "exposures": e,
               "options": scene_options(shifted, grid)} for _, grid, _, (f, x, m, e) in jobs]
    rendered = bootstrap.render_many(models, options=shifted, workers=solver.workers, progress=update,
                                     executor=solver.executor)
    problems, fits = [], []
    for (_, grid, region, (f, x, m, e)), model in zip(jobs, rendered):
        k_fit, c_fit = grid.gather(k)[region], grid.gather(confidence)[region]
        gain = np.where(c_fit > 0, 1.0 / k_fit, 1.0)
        synthetic = bootstrap.synthetic_burst(model, gain, np.random.default_rng(BOOTSTRAP_SEED))
        problems.append({"frames": synthetic, "motion": m, "saturation": burst.saturation, "excluded": x,
                         "exposures": e})
        # pixels whose every usable reading the model sees, a kernel's reach inside
        missed = np.any(usable(f, burst.saturation, x) & ~model.seen, axis=0).astype(np.float32)
        fits.append((grid, k_fit, c_fit, window_sum(missed, 2 * BOOTSTRAP_MARGIN + 1) == 0))
    # a square the model could not render (no pixel seen twice) measures nothing (None)
    results = each_or_none(solve_accurate_many, problems, options=solver.accurate, workers=solver.workers,
                           progress=update, executor=solver.executor)
    pieces, grids = {}, {}  # grid name -> its regions' (sigma_k, error) where measured
    for (grid, k_fit, c_fit, seen), result in zip(fits, results):
        if result is None:
            continue
        use = seen & (c_fit > 0) & (result.confidence > 0)
        error = (result.k / k_fit - 1)[use]  # about its square's mean: each fit's gauge is its own
        pieces.setdefault(grid.name, []).append((sigma_from_confidence(c_fit)[use], error - error.mean()))
        grids[grid.name] = grid
    out = {}
    for name, parts in pieces.items():
        sigma, error = (np.concatenate(p) for p in zip(*parts))
        measured = bootstrap.calibration(sigma, error, np.ones(sigma.shape, bool))
        if measured is not None:
            out.update(dict.fromkeys(grids[name].positions, measured))
    return out


#: Seed of :func:`bootstrapped`'s noise draws, the same for every grid: planes alike but for a power of
#: two in scale (RGB channels of a grey scene) are measured alike.
BOOTSTRAP_SEED = 20261127
#: Pixels of :func:`bootstrapped`'s regions within this many px of a reading the model does not see are
#: not measured: the cubic kernel's reach (its comparisons there have fewer partners than the fit's).
BOOTSTRAP_MARGIN = 2


def solve_raw(burst, frames, excluded, exposures, used: slice, in_frame, solver: Solver, progress, *,
              regions: dict | None = None):
    """Every grid's k and confidence as the solver gives them (no FPN model), frame-shaped, each
    plane's report, and the photosites the scene model shows hot (``solver.defects``); ``regions``
    as for :func:`solve_planes`."""
    return solve_raws(burst, frames, excluded, exposures, [used], in_frame, solver, progress, regions=regions)[0]


def solve_raws(burst, frames, excluded, exposures, useds, in_frame, solver: Solver, progress, *,
               regions: dict | None = None) -> list:
    """:func:`solve_raw` of each of the frame slices ``useds``. The accurate and scene solvers take
    every grid's tiles in one go, so that grids (a CFA's planes) and regions of one tile each run on
    every worker."""
    jobs = _jobs(burst, frames, excluded, exposures, useds, in_frame, solver, regions)
    if solver.method in ("accurate", "scene") and len(jobs) > 1:  # every grid's tiles on every worker
        update = progress("solve halves" if len(useds) > 1 else "solve", 0) if progress else None
        problems = [dict(frames=f, motion=m, saturation=burst.saturation, excluded=x, exposures=e,
                         options=scene_options(solver.scene, grid)) for _, grid, _, (f, x, m, e) in jobs]
        many = solve_accurate_many if solver.method == "accurate" else solve_scene_many
        kwargs = dict(options=solver.accurate if solver.method == "accurate" else solver.scene,
                      workers=solver.workers, progress=update, executor=solver.executor)
        # of a grid's squares, one with nothing to compare leaves the others; a grid with none fails as a plane does
        results = many(problems, **kwargs) if regions is None else each_or_none(many, problems, **kwargs)
        fitted = {(i, grid.name) for (i, grid, _, _), result in zip(jobs, results) if result is not None}
        if len(fitted) < len({(i, grid.name) for i, grid, _, _ in jobs}):
            raise EstimationError("no pixel could be compared between frames (all clipped, dark or out of view)")
    else:
        results = [solve_grid(f, x, m, burst.saturation, solver, progress, grid, exposures=e)
                   for _, grid, _, (f, x, m, e) in jobs]
    out = [(np.ones(frames.shape[1:], np.float32), np.zeros(frames.shape[1:], np.float32), {},
            np.zeros(frames.shape[1:], bool)) for _ in useds]
    for (i, grid, region, _), result in zip(jobs, results):
        if result is None:  # a square with nothing to compare (each_or_none): k = 1, confidence 0 there
            continue
        k, confidence, solved, hot = out[i]
        grid_hot = np.zeros(result.k.shape, bool)
        if solver.defects and result.offsets is not None and abs(grid.S[0, 0]) == 1:  # not a CFA colour's
            grid_hot = offset_shown(result.offsets)
        parts = (result.k, result.confidence, grid_hot)
        if grid_hot.any():  # copies only then (a 12 MP plane is 48 MB)
            parts = (np.where(grid_hot, 1, result.k), np.where(grid_hot, 0, result.confidence), grid_hot)
        for plane, part in zip((k, confidence, hot), parts):
            if region is not None:  # the region's, and elsewhere the grid's other regions' or k = 1, confidence 0
                whole = grid.gather(plane)
                whole[region] = part
                part = whole
            grid.scatter(plane, part)
        solved.update({name: PlaneReport(solver.method, grid.name, result.stats) for name in grid.positions})
    return out


def _jobs(burst, frames, excluded, exposures, useds, in_frame, solver: Solver, regions: dict | None) -> list:
    """``(which of useds, grid, region, (frames, left out, motion, exposures))`` of every grid, or every
    one of its ``regions`` (None: all of it), for each of the frame slices ``useds``."""
    jobs = []
    for i, used in enumerate(useds):
        fit = frames[used]  # a slice: a view
        left_out = None if excluded is None else np.broadcast_to(excluded[used, ..., None], fit.shape)  # every channel
        dark = too_dark(burst, fit, solver.floors)
        motion = in_frame.select(range(len(frames))[used])
        for grid in grids_of(burst, frames, solver.method):
            if regions is not None and grid.name not in regions:
                continue
            for region in [None] if regions is None else regions[grid.name]:
                grid_motion = motion.conjugate(grid.S)
                if region is None:
                    grid_frames = grid.gather(fit)
                    grid_left_out = None if left_out is None else grid.gather(left_out)
                    grid_dark = None if dark is None else grid.gather(dark)
                else:
                    rows, columns = region
                    grid_frames = _gather_region(grid, fit, rows, columns)
                    grid_left_out = None if left_out is None else _gather_region(grid, left_out, rows, columns)
                    grid_dark = None if dark is None else grid.gather(dark)[rows, columns]
                    grid_motion = grid_motion.conjugate(np.array([[1.0, 0, columns.start], [0, 1.0, rows.start],
                                                                  [0, 0, 1]]))
                if grid_dark is not None and grid_dark.any():  # every reading of a photosite too dark, left out
                    grid_left_out = np.broadcast_to(grid_dark, grid_frames.shape) if grid_left_out is None \
                        else grid_left_out | grid_dark
                jobs.append((i, grid, region, (grid_frames, grid_left_out, grid_motion, exposures[used])))
    return jobs


def _gather_region(grid, stack, rows: slice, columns: slice) -> np.ndarray:
    """``grid.gather(stack)[:, rows, columns]`` a frame at a time: the green lattice's gather is a
    copy (49 MB a 12 MP frame), and the whole stack's would hold every frame's plane for a 256 px
    region (196 MB for a half of 8 frames, 294 MB for the check's 6)."""
    return np.stack([grid.gather(one)[rows, columns] for one in stack])


def central(burst, frames, solver: Solver, side: int | None = None) -> dict:
    """The central ``side`` (default :data:`CHECK_SIDE`) px of every grid, (rows, columns) by grid name."""
    side = CHECK_SIDE if side is None else side
    return {grid.name: tuple(slice(max(0, (n - side) // 2), min(n, (n + side) // 2)) for n in grid.shape)
            for grid in grids_of(burst, frames, solver.method)}


def measured_regions(burst, frames, solver: Solver) -> dict:
    """Where k's error is measured (on halves, on the burst the scene model predicts): each grid's
    :func:`measured_squares` by grid name, or its central square where one of those is not all photosites
    (a CFA's greens together lie on a lattice turned 45 degrees, its other squares off the sensor or at
    its edges: with those at the edges a 12 MP DNG's most precise tenth erred 1.35x, centrally 1.09x)."""
    regions, middle = {}, central(burst, frames, solver)
    for grid in grids_of(burst, frames, solver.method):
        squares = measured_squares(grid.shape)
        photosites = grid.gather(np.ones(frames.shape[1:], np.float32)) if len(squares) > 1 else None  # once
        if photosites is not None and not all(photosites[square].all() for square in squares):
            squares = [middle[grid.name]]
        regions[grid.name] = squares
    return regions


def measured_squares(shape) -> list:
    """The (rows, columns) slices of a grid of ``shape`` k's error is measured on: all of an axis up to
    :data:`MEASURED_WHOLE` x :data:`CHECK_SIDE`, else CHECK_SIDE px about the centre of each of its equal
    cells, one per :data:`MEASURED_SPACING` px of it (at least one)."""
    spans = []
    for n in shape:
        count = max(1, round(n / MEASURED_SPACING))
        starts = [min(max(int((j + 0.5) * n / count) - CHECK_SIDE // 2, 0), n - CHECK_SIDE) for j in range(count)]
        spans.append([slice(0, n)] if n <= MEASURED_WHOLE * CHECK_SIDE
                     else [slice(start, start + CHECK_SIDE) for start in starts])
    return [(rows, columns) for rows in spans[0] for columns in spans[1]]


#: Side (px of each grid) of the central region the hold-out check fits again without the reference:
#: enough blocks for a standard error of the ratio near 1 % (256 blocks of 16 px), at a small cost
#: on large frames (a 12 MP mosaic's planes are 2000 px wide).
CHECK_SIDE = 256
#: Longest axis of a grid, in :data:`CHECK_SIDE`, whose error is measured along all of it, not only its
#: central CHECK_SIDE px (384 px): the strips beside the frame's edges, where trajectories are shortest
#: and the motion estimate errs most, are then a large share of its pixels (on a 240x320 frame, the
#: 8-32 px from the left and right edges: 15 %), and cost at most 1.5x the region's fits. On 240x320
#: 8-bit bursts of 16 frames the least precise tenth erred 1.12-1.16x the written sigma_k measured along
#: all 320 px, 1.12-1.30x on the central 256 (docs/limits.md, "Confidence").
MEASURED_WHOLE = 1.5
#: Spacing (px of a grid) of the squares k's error is measured on along an axis (:func:`measured_squares`):
#: a large frame's scene sampled across it. On the bench's 4000x3000x8 dead-leaves burst (leaves up to
#: 1000 px; `balanced`) the central 256 px set tenths of 0.69-1.07, six squares 0.87-1.03, for 1.09x the
#: time. A 12 MP mosaic's colour planes and its greens' lattice (the accurate solver's) keep one.
MEASURED_SPACING = 1536


def scene_options(options: SceneOptions, grid) -> SceneOptions:
    """The scene solver's options on ``grid``: a photosite is ``1 / scale`` of the grid's pitch wide
    (a CFA plane's photosites are every other one of the mosaic)."""
    return dataclasses.replace(options, aperture=1.0 / float(abs(grid.S[0, 0])))


def solve_grid(frames, excluded, motion, saturation, solver: Solver, progress, grid,
               exposures=None) -> GainResult:
    update = progress(f"solve {grid.name}", 0) if progress else None
    if solver.method == "scene":
        return solve_scene_many([dict(frames=frames, motion=motion, saturation=saturation, excluded=excluded,
                                      exposures=exposures, options=scene_options(solver.scene, grid))],
                                workers=solver.workers, progress=update, executor=solver.executor)[0]
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


