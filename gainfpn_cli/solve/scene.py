"""The scene solver (``solver.method: scene``): one forward model of the whole burst instead of
pairwise comparisons (docs/method.md section 8b).

Every reading is the gain times the light its photosite collects from one latent scene ``S``,
sampled ``scale`` times finer than the grid's pixel pitch in the coordinates of the first frame:

    y_t(p) = e_t a(p) (B W_t S)(p) + noise,      k = 1 / a

``W_t`` puts pixel ``p`` of frame ``t`` where the motion says it sees the first frame, ``B``
integrates the linear spline through ``S`` over the photosite's box (``aperture`` grid px wide:
1 for a full plane, 1/2 for a CFA plane whose photosites are every other one). The box of a
linear spline has a closed form, so each reading is an exact weighted sum of ``(ceil(w) + 2)^2``
scene samples: a sparse row. Pairwise comparisons resample one aliased frame onto another's
grid, which no kernel can do; the latent scene is super-resolved by the burst's own sub-pixel
shifts, so the readings of every frame are explained together.

``a`` and ``S`` are found by Gauss-Newton on the noise-weighted squares, with a weak gradient
prior on ``S`` (fine detail the shifts do not sample) and a prior ``a ~ N(1, gain_prior)``
(the gauge: a and S trade their common low band). Each step eliminates ``a`` (its block is
diagonal) and solves the Schur complement for ``S`` by preconditioned conjugate gradients, so
the coupling between gains and scene is solved, not alternated. Between steps each frame's warp
(a quadratic correction over the tile) and exposure are refined against the fitted model where
the data show them off, which is the joint motion refinement the pairwise form cannot converge.
The final gauge divides ``k`` by its own low-pass, as the accurate solver's does.

The plane is cut into overlapping tiles (:mod:`solve.tiling`), solved independently and in
parallel; the result does not depend on the number of workers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..geometry.resample import low_pass, window_sum
from .result import GainResult, SceneStats, confidence_from_sigma
from .scenemodel import fit_tile, gain_information, gauss_newton_path, gauss_newton_step
from .tiling import Tile, blend, checked_problem, ramp_sums, solve_tiles, tiles_of


@dataclass(frozen=True)
class SceneOptions:
    """Options of the scene solver.

    Attributes
    ----------
    scale : int
        Scene samples per grid pixel pitch, on each axis.
    aperture : float
        Width of a photosite's light-collecting box, in grid pixels (1: a full plane; 0.5: one
        colour of a 2x2 CFA, the solver sets it from the grid).
    smoothness : float
        Weight of the squared gradient of ``S`` (in scene samples), relative to one reading of
        median noise weight.
    gain_prior : float
        Standard deviation of the prior ``a ~ N(1, gain_prior)``: it pins what the data cannot
        (the low band, unseen pixels, the modes in which ``a`` and ``S`` trade); its pull on each
        pixel's own ``a`` is taken back after the fit, as the FPN model shrinks k itself.
    steps : int
        Gauss-Newton steps (the first with uniform weights, then with the fitted noise model).
    cg_iterations : int
        Conjugate-gradient iterations per step at most.
    cg_rtol : float
        Their relative tolerance on the residual.
    robust_scale : float or None
        After the first step, readings get Cauchy weights ``1 / (1 + (r / (c sigma))^2)``
        (``c``: this, ``sigma``: the noise model's), which discount what the model cannot
        explain (a mis-registered edge, a mover left in); None: plain least squares.
    gauge_sigma : float
        Gaussian sigma (px) of the low band that is gauged to 1.
    tile, halo : int
        Side of the tiles' cores and the halo around each (px).
    gain_range : (float, float)
        Gains outside it are left unestimated.
    refine_frames : bool
        Refine every frame's warp over the tile and its exposure against the model
        (:func:`solve.frames.refine_frames`, docs/method.md section 8b): before the first step the
        exposures, after it any significant change, after the last a material one, which adds a
        step, up to ``extra_steps``. ``refine_warps``: ``"field"`` the quadratic field over the
        tile, ``"shift"`` only each frame's mean move over the tile (the burst the model predicts,
        :func:`solving.bootstrapped`).
    refine_px, refine_exposure : float
        The RMS move (grid px) and the exposure change that make a change material: after the last
        step one below both is left; after the first, a move above ``refine_px`` starts the fit
        again with the moves found before it.
    """

    scale: int = 2
    aperture: float = 1.0
    smoothness: float = 1e-4
    gain_prior: float = 0.05
    steps: int = 2
    cg_iterations: int = 20
    cg_rtol: float = 1e-4
    robust_scale: float | None = 3.0
    gauge_sigma: float = 32.0
    # 256 px: each tile's warp refinement follows a lens distortion more closely than a 384 px one's
    # (a homography forced on a 1 px distortion: 1.15 -> 0.99 % residual), for 9 -> 13 % of a
    # 12 MP plane in halos (docs/limits.md, "The scene solver")
    tile: int = 256
    halo: int = 8
    gain_range: tuple[float, float] = (0.5, 2.0)
    refine_frames: bool = True
    refine_warps: Literal["field", "shift"] = "field"
    # up to 4 more steps while frames still move: 1 px of distortion under a forced homography
    # (640x480x8, bench) 1.87 % -> 0.98 %
    extra_steps: int = 4
    # on bursts whose warps are the truth (96x128 paper bursts, seeds 1-3) noise and the first
    # step's blurred scene give moves of 0.02-0.055 px and exposure changes to 0.1 %
    refine_px: float = 0.05
    refine_exposure: float = 0.002

    @property
    def colour_plane(self) -> bool:
        """The grid is a CFA colour plane (its photosites every other grid pixel: ``aperture`` below 1),
        whose latent scene is still aliased: its misfit is neither refined away as a misregistration
        nor its residual excess shrunk towards a broader window's."""
        return self.aperture < 1


def solve_scene(frames, motion, *, options: SceneOptions = SceneOptions(), saturation=None, excluded=None,
                exposures=None, workers: int = 2, progress=None, executor=None) -> GainResult:
    """Estimate ``k`` of one grid by the scene model; arguments as :func:`solve.accurate.solve_accurate`."""
    return solve_scene_many([dict(frames=frames, motion=motion, saturation=saturation, excluded=excluded,
                                  exposures=exposures)], options=options, workers=workers, progress=progress,
                            executor=executor)[0]


def solve_scene_many(problems, *, options: SceneOptions = SceneOptions(), workers: int = 2, progress=None,
                     executor=None) -> list[GainResult]:
    """:func:`solve_scene` of each of ``problems`` (dicts as for :func:`solve.accurate.solve_accurate_many`,
    each with its own ``options`` if it has them), their tiles solved in one go."""
    prepared = [prepare(p, options) for p in problems]
    shapes = iter([np.shape(p["frames"])[1:] for p in problems])
    return solve_tiles(prepared, _solve_tile, lambda tiles, results: _assemble(tiles, results, next(shapes)),
                       workers=workers, progress=progress, executor=executor)


def _assemble(tiles, results, shape) -> GainResult:
    opt = tiles[0].options
    origins = [(t.y0, t.x0) for t in tiles]
    scored = [r[3] for r in results]  # blend frees the results as it goes
    # each pixel's score from the tiles that scored it (0: no line fitted there)
    (offsets,), weight = ramp_sums(origins, scored, lambda r: (r,), lambda r: r != 0, shape, opt.halo)
    offsets = np.divide(offsets, weight, out=np.zeros(shape, np.float32), where=weight > 0)
    b = blend(origins, results, shape, halo=opt.halo, gain_range=opt.gain_range)
    return GainResult(b.k, b.confidence, SceneStats(len(tiles), b.iterations, b.unestimated_pixels,
                                                    b.out_of_range_pixels, b.median_confidence), offsets)


def prepare(problem: dict, options: SceneOptions) -> list[Tile]:
    """The tiles of one of :func:`solve_scene_many`'s ``problems`` (its own ``options`` if it has them),
    its inputs checked."""
    options = problem.get("options", options)
    excluded = problem.get("excluded")
    if options.scale < 1 or not 0 < options.aperture <= 1:
        raise ValueError(f"scale must be >= 1 and aperture in (0, 1], got {options.scale}, {options.aperture}")
    frames, motion, exposures = checked_problem(problem["frames"], problem["motion"], excluded,
                                                problem.get("exposures"))
    return tiles_of(frames, excluded, motion, problem.get("saturation"), options, exposures)


def _solve_tile(tile: Tile) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """k, confidence, conjugate-gradient iterations and :func:`offset_scores` of one tile (its halo
    included)."""
    opt = tile.options
    n_frames, h, w = tile.frames.shape
    fit = fit_tile(tile)
    if fit is None:
        return np.ones((h, w)), np.zeros((h, w)), 0, np.zeros((h, w), np.float32)
    a, est, iterations = fit.a, fit.est, fit.iterations
    # the prior pulls each a towards 1 by the information of its readings over that plus the prior's;
    # the FPN model shrinks k by its sigma_k, so the pull is taken back here (docs/method.md 8b)
    information = gain_information(fit.weight, fit.predicted, a.size)
    unpull = np.divide(information + 1.0 / opt.gain_prior**2, information, out=np.ones_like(information),
                       where=information > 0)
    a = 1.0 + (a - 1.0) * unpull
    # the noise's own path into a: the same linear step, driven by a draw of the noise model alone
    # (seeded by the tile's place, so that any worker draws the same)
    rng = np.random.default_rng([PROBE_SEED, tile.y0, tile.x0])
    da, fitted, its = _noise_probe(fit, a, unpull, rng, opt)
    iterations += its
    # ... and the gains' own: the share of a change in a that the step gives back to a (the scene
    # takes up the rest where few readings see each scene sample, or where they are dark); k and its
    # error are divided by it, so the FPN model gets k unbiased
    response, its = _gain_response(fit, a, est.reshape(h, w), unpull, rng, opt)
    iterations += its
    a = 1.0 + (a - 1.0) / response
    da = da / response
    k = 1.0 / np.where(est & (a > 0), a, 1.0).reshape(h, w)
    est = est.reshape(h, w) & (a.reshape(h, w) > 0)
    k = k / low_pass(k, opt.gauge_sigma, est)  # the gauge: low band exactly 1
    k[~est] = 1.0
    # pixels that read black in some frame: left out there, and their readings kept are biased
    # (a left-out reading, a defect's or a mover's, is not one the solve could have used)
    seen = np.ones(tile.frames.shape, bool) if tile.excluded is None else ~tile.excluded
    black = (tile.frames <= 0) & seen
    at_black = black.any(axis=0)
    actual, expected = _residual_sums(fit, fitted, (h, w))
    prior_dof = 0.0 if opt.colour_plane else EXCESS_PRIOR_DOF  # see EXCESS_PRIOR_DOF
    sigma_k = _sigma(da, _excess(actual, expected, at_black, prior_dof=prior_dof), a, est)
    # ... and the share of their gain that readings near black do not see, times the gains' spread
    censored = _censored_per_pixel(fit, black, seen, a)
    if (censored < 1).any():
        sigma_k = np.sqrt(sigma_k**2 + (1 - censored) ** 2 * _fpn_variance(k, sigma_k, censored, est))
    confidence = np.where(est, confidence_from_sigma(sigma_k), 0.0)
    # the offsets' test takes each pixel's neighbours' excess (its own offset would excuse itself)
    offsets = offset_scores(fit, _excess(actual, expected, at_black, own=False, prior_dof=prior_dof))
    return k.astype(np.float32), confidence.astype(np.float32), iterations, offsets


#: Fewest readings of a pixel :func:`offset_scores` scores: with 4 (a 5-frame burst, one frame held out),
#: the latent scene's 4 samples a pixel take up most of them, and the test flagged 5-17 healthy
#: photosites of 76 800 on 240x320 paper dead leaves (seeds 3-6, through the pipeline); with 5, 0-3.
OFFSET_MIN_READINGS = 5


def offset_scores(fit, excess: np.ndarray) -> np.ndarray:
    """Per pixel, how plainly its readings carry an offset besides the gain: the intercept ``b`` of
    the line ``y_t = a x_t + b`` fitted by weighted least squares to its readings ``y_t`` against the
    fitted scene ``x_t`` it sees (``B W_t S``, each reading weighted by the noise model's inverse
    variance), over its standard error; float32, 0 where the pixel's scene does not vary along its
    trajectory or fewer than :data:`OFFSET_MIN_READINGS` readings count. A healthy pixel scores about
    N(0, 1); a hot one's dark-current offset scores as far as the scene crossing its trajectory tells
    it from a gain (docs/method.md section 12b)."""
    shape, n = excess.shape, excess.size
    weight = np.where(fit.valid, 1.0 / fit.variance, 0.0).reshape(-1, n)
    x, y = fit.predicted.reshape(-1, n), fit.y.reshape(-1, n)
    total = weight.sum(axis=0)
    safe = np.where(total > 0, total, 1.0)
    x_mean, y_mean = (weight * x).sum(axis=0) / safe, (weight * y).sum(axis=0) / safe
    spread = (weight * (x - x_mean) ** 2).sum(axis=0)
    # a spread below 1e-9 of the squared level is rounding: the scene is flat along the trajectory
    use = ((weight > 0).sum(axis=0) >= OFFSET_MIN_READINGS) & (spread > 1e-9 * total * x_mean**2)
    spread = np.where(use, spread, 1.0)
    slope = (weight * (x - x_mean) * (y - y_mean)).sum(axis=0) / spread
    intercept = y_mean - slope * x_mean
    variance = 1.0 / safe + x_mean**2 / spread
    score = np.where(use, intercept / np.sqrt(variance), 0.0).reshape(shape)
    typical = float(np.median(excess[use.reshape(shape)])) if use.any() else 0.0
    relative = excess / typical if typical > 0 else np.ones(shape)  # residuals all 0: readings the model explains
    return (score / np.sqrt(np.maximum(relative, 1.0))).astype(np.float32)


#: Seed of the noise probe of :func:`_solve_tile` (with the tile's origin).
PROBE_SEED = 20261124
#: Conjugate-gradient iterations after which the probe's tile sums are taken (:func:`_noise_probe`),
#: the last its cap. Unconverged, the sums run low (da's squares) and high (the residuals' share of
#: the noise): at 20 they put sigma_k^2 at 0.59-0.62x the converged on 4 fitted frames (640x480
#: dead leaves and gravel, seed 3; 0.84x on 7), and sigma_k under-predicted by up to 1.6x (tenths
#: 1.13-1.64, 240x320 dead leaves, seeds 3-5); extrapolated from 20, 25 and 30 they give
#: 0.986-1.023x on 5, 8 and 16 frames, bright, dark and a photograph (60 iterations: 0.972-1.003x)
PROBE_STOPS = (20, 25, 30)
#: Largest ratio of successive changes taken as the sums' geometric convergence (:func:`converged`):
#: per 5 iterations they shrink by 0.5-0.8, and on a photograph about linearly; 0.8 overshot there
#: (1.052x), 0.7 kept every tile above within 3 %
PROBE_RATE = 0.7


def converged(values, rate: float = PROBE_RATE) -> float:
    """The limit of a sequence that converges geometrically, from its last three ``values`` at evenly
    spaced iterations (Aitken's extrapolation, the ratio of successive changes at most ``rate``): the
    last value where they do not shrink in one direction, and never below half of it or over twice."""
    x1, x2, x3 = values[-3:]
    d1, d2 = x2 - x1, x3 - x2
    if d1 == 0 or d2 / d1 <= 0:
        return float(x3)
    ratio = min(d2 / d1, rate)
    return float(np.clip(x3 + d2 * ratio / (1 - ratio), x3 / 2, 2 * x3))


def _noise_probe(fit, a, unpull, rng, opt) -> tuple[np.ndarray, np.ndarray, int]:
    """The noise's own path into a: the last step, driven by a draw of the noise model alone. Its
    ``da`` (with the prior's pull taken back) and what of the draw the fit leaves in the readings
    (``fitted``), each scaled so that its sum of squares over the tile is that of the converged step,
    extrapolated along :data:`PROBE_STOPS` (:func:`converged`); and the iterations taken."""
    n_frames = fit.y.size // a.size
    use = fit.weight > 0
    probe = np.where(use, rng.standard_normal(fit.y.size) * np.sqrt(fit.variance), 0.0)
    path, its = gauss_newton_path(fit.A, fit.weight, probe, fit.predicted, a, fit.s, opt, priors=False,
                                  stops=PROBE_STOPS, lam=fit.lam)
    moved, left = [], []
    for _, da, seen in path:  # da and fitted are left at the last stop's
        fitted = probe - np.tile(a, n_frames) * seen - fit.predicted * np.tile(da, n_frames)
        moved.append(float(np.sum((da * unpull)[fit.est] ** 2)))
        left.append(float(np.sum(fitted[use] ** 2 / fit.variance[use])))
    scale_da = np.sqrt(converged(moved) / moved[-1]) if moved[-1] > 0 else 1.0
    scale_fitted = np.sqrt(converged(left) / left[-1]) if left[-1] > 0 else 1.0
    return da * unpull * scale_da, fitted * scale_fitted, its


#: Least share of a gain change the step is taken to give back (:func:`_gain_response`): below it
#: the estimate is noise divided by nearly nothing. Measured medians 0.99 (96x128 dead leaves, 5
#: frames, 75 % exposure, seeds 1-3), 0.93-0.94 (15 %), 0.70-0.75 (240x320 camera, 5 frames, 7.5 %;
#: 0.3-6 % of a tile's pixels at this floor).
MIN_GAIN_RESPONSE = 0.25


def _gain_response(fit, a, est, unpull, rng, opt) -> tuple[np.ndarray, int]:
    """Per pixel, the share of a change in its ``a`` that the last step gives back to ``a`` (9x9
    windows; at least :data:`MIN_GAIN_RESPONSE`), and the step's conjugate-gradient iterations.

    The step is driven by the readings' change under a random pattern ``a -> a (1 + d)``, ``d = +-1``
    per pixel; without priors it would return ``d`` exactly, but the gains' prior makes the latent
    scene take part of it up, which the per-pixel ``unpull`` does not restore. The fit's iterations
    suffice here: 80, as for the noise probe, gave dark 5-frame tenths 0.93-1.14 against 0.97-1.18
    and MSE ratios 0.5-1 % better, for 1.18x the estimate's time at 640x480x8."""
    n = a.size
    n_frames = fit.y.size // n
    pattern = rng.choice([-1.0, 1.0], size=n) * a
    drive = np.where(fit.weight > 0, np.tile(pattern, n_frames) * fit.predicted, 0.0)
    _, given, its = gauss_newton_step(fit.A, fit.weight, drive, fit.predicted, a, fit.s, opt, priors=False,
                                      lam=fit.lam)
    given = (given * unpull * pattern).reshape(est.shape)
    total = window_sum(np.where(est, pattern.reshape(est.shape) ** 2, 0.0), 9)
    response = np.divide(window_sum(np.where(est, given, 0.0), 9), total, out=np.ones(est.shape), where=total > 0)
    return np.clip(response, MIN_GAIN_RESPONSE, 1.0).reshape(-1), its


def censored_response(black_fraction) -> np.ndarray:
    """How much of a change in its gain a reading kept above black follows (1: all of it), from
    the fraction of the readings of its light that read black.

    With readings ``y = g L + n``, ``n ~ N(0, sigma)``, a fraction ``f`` at black puts the light at
    ``z = L / sigma = Phi^-1(1 - f)``; those kept have the mean ``sigma (z + lambda(z))``
    (``lambda = phi / Phi``, the inverse Mills ratio), which moves with the gain by ``L delta(z)``,
    ``delta = 1 - lambda (lambda + z)``. The fit, which takes the kept mean for the light, sees
    ``z delta / (z + lambda)`` of a gain change: 1 without readings at black, 0.56 with one in 8,
    0 from half of them."""
    from scipy.special import log_ndtr, ndtri

    f = np.asarray(black_fraction, dtype=np.float64)
    z = np.where((f > 0) & (f < 0.5), ndtri(1 - np.clip(f, 1e-12, 0.5)), 1.0)
    mills = np.exp(-z**2 / 2 - 0.5 * np.log(2 * np.pi) - log_ndtr(z))
    response = np.clip(z * (1 - mills * (mills + z)) / (z + mills), 0.0, 1.0)
    return np.where(f <= 0, 1.0, np.where(f >= 0.5, 0.0, response))


def _censored_per_pixel(fit, black, seen, a) -> np.ndarray:
    """Each pixel's :func:`censored_response`: the fraction of black among the readings (``seen``,
    ``(F, H, W)``) that see each scene sample, carried to the readings kept, averaged per pixel
    over its readings by their information on its gain."""
    if not black.any():  # every reading follows its gain
        return np.ones(seen.shape[1:])
    sees = fit.A.back(seen.reshape(-1).astype(np.float64))
    fraction = np.divide(fit.A.back(black.reshape(-1).astype(np.float64)), sees, out=np.zeros(sees.size),
                         where=sees > 0)
    n_frames = seen.shape[0]
    information = np.where(fit.weight > 0, fit.weight * (fit.predicted * np.tile(a, n_frames)) ** 2, 0.0)
    information = information.reshape(n_frames, -1)
    followed = (information * censored_response(fit.A.forward(fraction)).reshape(n_frames, -1)).sum(axis=0)
    total = information.sum(axis=0)
    return np.divide(followed, total, out=np.ones_like(total), where=total > 0).reshape(seen.shape[1:])


def _fpn_variance(k, sigma_k, followed, est) -> float:
    """The variance of the tile's gains, from its pixels whose readings follow half their gain or
    more (``followed``, :func:`censored_response` per pixel): ``k - 1`` there is ``followed (1 / a - 1)``
    plus an error of variance ``sigma_k^2``."""
    use = est & np.isfinite(sigma_k) & (followed > 0.5)
    if not use.any():
        return 0.0
    return max(float(np.sum((k[use] - 1) ** 2 - sigma_k[use] ** 2) / np.sum(followed[use] ** 2)), 0.0)


def _sigma(da, excess, a, est) -> np.ndarray:
    """``sigma_k`` from the noise probe (inf where ``est`` is False): ``da`` is how a draw of the
    noise model moves ``a``; its square averaged over a 9x9 window is a's variance if the noise model
    is right, scaled by the window's ``excess`` (:func:`_excess`), so that pixels by features
    the model cannot explain, or readings noisier than the model, report their larger error."""
    shape = est.shape
    moved = np.where(est, da.reshape(shape) ** 2, 0.0)
    variance_a = np.divide(window_sum(moved, 9), window_sum(est.astype(np.float64), 9), out=np.full(shape, np.inf),
                           where=est)
    np.multiply(variance_a, excess, out=variance_a, where=est)  # inf stays inf where a is not estimated
    return np.sqrt(np.maximum(variance_a, 0.0)) / np.maximum(a.reshape(shape), 1e-3) ** 2


def _residual_sums(fit, fitted, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of a tile of ``shape``, the sums over its readings that count of the data's squared
    residuals and of the noise probe's (``fitted``, which the fit shrinks by the same leverage as the
    data's), in units of the noise model's variance: :func:`_excess`'s ``actual`` and ``expected``."""
    use = (fit.weight > 0).reshape(-1, fit.a.size)

    def per_pixel(values):
        return np.where(use, values.reshape(use.shape), 0.0).sum(axis=0).reshape(shape)

    return per_pixel(fit.residual**2 / fit.variance), per_pixel(fitted**2 / fit.variance)


#: The residual excess of :func:`_excess`: its window (px), the broader window it is shrunk towards
#: (px), and the weight of that broader ratio in residual degrees of freedom. A 5x5 window holds 180-290
#: of them at 15 fitted frames but 2-12 at 4 (240x320 gravel, 40 % of full scale), whose ratio then
#: scatters by half and sorted sigma_k by its own noise (tenths 0.73-1.26; 0.79-1.11 shrunk, camera at
#: 16 frames unchanged; weights 20 and 13 px chosen on gravel, coins and grass at 5 frames). Not on a CFA
#: colour plane, whose excess is the aliased detail's misfit where it is: shrunk, the bench's 8-frame
#: raw12 dead-leaves burst under the scene solver left 0.89 % residual FPN instead of 0.84 %.
EXCESS_WINDOW, EXCESS_BROAD, EXCESS_PRIOR_DOF = 5, 13, 20.0


def _excess(actual, expected, at_black, own: bool = True, prior_dof: float = EXCESS_PRIOR_DOF) -> np.ndarray:
    """The residuals' variance over what the noise model predicts for them, per pixel: ``actual`` and
    ``expected`` are each pixel's sums over its readings (:func:`_residual_sums`), pooled over
    :data:`EXCESS_WINDOW` and shrunk towards their ratio over :data:`EXCESS_BROAD` with the weight of
    ``prior_dof`` degrees of freedom: ``(A + D R) / (E + D)``; without the pixel's own
    readings if not ``own``. Where a window holds a pixel that read black (``at_black``) the ratio is
    at least 1: the readings there that stay above black are the noise's high draws, which a fitted
    scene explains exactly, so their residuals read smaller than the noise (docs/method.md 8b)."""
    own_actual, own_expected = (0.0, 0.0) if own else (actual, expected)
    local_actual = window_sum(actual, EXCESS_WINDOW) - own_actual
    local_expected = window_sum(expected, EXCESS_WINDOW) - own_expected
    broad_expected = window_sum(expected, EXCESS_BROAD) - own_expected
    broad = np.divide(window_sum(actual, EXCESS_BROAD) - own_actual, broad_expected, out=np.ones(actual.shape),
                      where=broad_expected > 0)
    pooled = local_expected + prior_dof
    # a window without readings sums to the box filter's rounding (about 1e-15 of the sums), not 0
    empty = 1e-9 * float(np.max(pooled, initial=0.0))
    excess = np.divide(local_actual + prior_dof * broad, pooled, out=np.ones(actual.shape), where=pooled > empty)
    return np.where(window_sum(at_black.astype(np.float32), EXCESS_WINDOW) > 0, np.maximum(excess, 1.0), excess)
