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

import numpy as np

from ..geometry.resample import low_pass, positions, window_sum
from .frames import refine_frames
from .result import GainResult, SceneStats, confidence_from_sigma
from .tiling import Tile, blend, checked_problem, solve_tiles, tiles_of


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
        After each step, refine every frame's warp over the tile and its exposure against the
        model (:func:`solve.frames.refine_frames`); a frame that moves adds a step, up to ``extra_steps``.
    refine_px, refine_exposure : float
        The RMS move (grid px) and the exposure change below which a frame is left as it is.
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
    tile: int = 256
    halo: int = 16
    gain_range: tuple[float, float] = (0.5, 2.0)
    refine_frames: bool = True
    # up to 4 more steps while frames still move: 1 px of distortion under a forced homography
    # (640x480x8, bench) 1.87 % -> 0.99 %, most of it in the first 2
    extra_steps: int = 4
    # steps smaller than these are left: on bursts whose warps are the truth (96x128 paper bursts,
    # seeds 1-3) noise and the first step's blurred scene give moves of 0.02-0.055 px and exposure
    # changes to 0.1 %
    refine_px: float = 0.05
    refine_exposure: float = 0.002


#: Median of a chi-square variable of one degree of freedom: a median of squared normal
#: residuals over it is their variance.
CHI2_MEDIAN = 0.4549364


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
    prepared = [_prepare(p["frames"], p["motion"], p.get("options", options), p.get("saturation"),
                         p.get("excluded"), p.get("exposures")) for p in problems]
    shapes = iter([np.shape(p["frames"])[1:] for p in problems])
    return solve_tiles(prepared, _solve_tile, lambda tiles, results: _assemble(tiles, results, next(shapes)),
                       workers=workers, progress=progress, executor=executor)


def _assemble(tiles, results, shape) -> GainResult:
    opt = tiles[0].options
    b = blend([(t.y0, t.x0) for t in tiles], results, shape, halo=opt.halo, gain_range=opt.gain_range)
    return GainResult(b.k, b.confidence, SceneStats(len(tiles), b.iterations, b.unestimated_pixels,
                                                    b.out_of_range_pixels, b.median_confidence))


def _prepare(frames, motion, options: SceneOptions, saturation, excluded, exposures) -> list[Tile]:
    if options.scale < 1 or not 0 < options.aperture <= 1:
        raise ValueError(f"scale must be >= 1 and aperture in (0, 1], got {options.scale}, {options.aperture}")
    frames, motion, exposures = checked_problem(frames, motion, excluded, exposures)
    return tiles_of(frames, excluded, motion, saturation, options, exposures)


def box_spline_weights(u: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Taps ``(n, m)`` and weights: the mean over ``[u - width/2, u + width/2]`` of the linear
    spline through unit samples at the integers, for each of the ``n`` positions ``u``."""
    m = int(np.ceil(width)) + 2
    taps = np.floor(u - width / 2).astype(np.int64)[:, None] + np.arange(m)
    lo = u[:, None] - width / 2 - taps
    return taps, (_hat_integral(lo + width) - _hat_integral(lo)) / width


def _hat_integral(x: np.ndarray) -> np.ndarray:
    """``int_-inf^x max(0, 1 - |s|) ds``."""
    x = np.clip(x, -1.0, 1.0)
    return np.where(x < 0, (x + 1) ** 2 / 2, 1 - (1 - x) ** 2 / 2)


def observation_matrix(points: list[np.ndarray], fine: tuple[int, int], scale: int, aperture: float):
    """The stacked sparse ``B W_t`` of every frame: row ``t * n + i`` is reading ``i`` of frame
    ``t``, whose pixel sees the first frame at ``points[t][i] = (x, y)`` (grid px); columns are the
    ``fine`` scene samples (row-major), sample ``j`` at grid coordinate ``(j - (scale-1)/2) / scale``.
    Also whether each row's support lies inside the scene grid (the others are zero rows)."""
    import scipy.sparse as sp

    fh, fw = fine
    width = scale * aperture
    m = int(np.ceil(width)) + 2
    offsets = (np.arange(m, dtype=np.int32)[:, None] * fw + np.arange(m, dtype=np.int32)).ravel()
    data, indices, inside = [], [], []
    for xy in points:
        tu, wu = box_spline_weights(scale * xy[:, 0] + (scale - 1) / 2, width)
        tv, wv = box_spline_weights(scale * xy[:, 1] + (scale - 1) / 2, width)
        seen = (tu[:, 0] >= 0) & (tu[:, -1] < fw) & (tv[:, 0] >= 0) & (tv[:, -1] < fh)
        corner = np.where(seen, tv[:, 0] * fw + tu[:, 0], 0).astype(np.int32)  # out of view: zero weights
        indices.append((corner[:, None] + offsets).ravel())
        wv = np.where(seen[:, None], wv, 0.0).astype(np.float32)
        data.append((wv[:, :, None] * wu.astype(np.float32)[:, None, :]).ravel())
        inside.append(seen)
    n = sum(len(xy) for xy in points)
    matrix = sp.csr_matrix((np.concatenate(data), np.concatenate(indices),
                            np.arange(0, n * m * m + 1, m * m, dtype=np.int32)), shape=(n, fh * fw))
    return matrix, np.concatenate(inside)


def gradient_gram(fine: tuple[int, int]):
    """``D^T D`` of the forward differences of a ``fine`` grid along both axes (sparse)."""
    import scipy.sparse as sp

    def diff(n):
        return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))

    D = sp.vstack([sp.kron(diff(fine[0]), sp.eye(fine[1])), sp.kron(sp.eye(fine[0]), diff(fine[1]))])
    return (D.T @ D).tocsr()


def noise_variance(residuals: np.ndarray, predicted: np.ndarray, bins: int = 8) -> tuple[float, float]:
    """``(alpha, beta)`` of the noise model ``var = alpha + beta * predicted`` (shot and read
    noise), fitted to the squared ``residuals`` by robust medians over quantile bins of the level."""
    edges = np.quantile(predicted, np.linspace(0, 1, bins + 1))
    which = np.clip(np.searchsorted(edges, predicted, side="right") - 1, 0, bins - 1)
    level, variance = [], []
    for b in range(bins):
        r = residuals[which == b]
        if r.size >= 8:
            level.append(np.median(predicted[which == b]))
            variance.append(np.median(r**2) / CHI2_MEDIAN)
    if len(level) < 2 or np.ptp(level) <= 0:
        return float(np.mean(variance)) if variance else 1.0, 0.0
    beta, alpha = np.polyfit(level, variance, 1)
    if beta < 0 or alpha < 0:  # a negative term is noise in the fit: the other carries it
        beta = max(beta, 0.0)
        alpha = max(float(np.median(np.array(variance) - beta * np.array(level))), 0.0)
    return float(alpha), float(beta)


def _solve_tile(tile: Tile) -> tuple[np.ndarray, np.ndarray, int]:
    """k, confidence and conjugate-gradient iterations of one tile (its halo included)."""
    opt = tile.options
    frames, good = tile.readings()
    n_frames, h, w = frames.shape
    region = (tile.y0, tile.x0, h, w)
    fine = (opt.scale * h, opt.scale * w)
    points = [positions(tile.motion.pair(t, 0, region), (h, w)).reshape(-1, 2) for t in range(n_frames)]
    A, inside = observation_matrix(points, fine, opt.scale, opt.aperture)
    A = _Sampling(A)
    valid = good.reshape(-1) & inside
    y = np.where(valid, frames.reshape(-1), 0.0)
    seen = valid.reshape(n_frames, -1).sum(axis=0)
    est = seen >= 2  # one reading: a would explain it alone
    if not est.any():
        return np.ones((h, w)), np.zeros((h, w)), 0

    s = _mean_along(A, valid.astype(np.float64), y, valid)
    a = np.ones(h * w)
    gram = gradient_gram(fine)
    iterations = 0
    noise = (np.var(y[valid]) * 1e-4, 0.0)  # the first step: uniform weights
    exposure = np.ones(n_frames)
    # a plane sampled every other photosite (aperture below 1) is aliased enough that its misfit
    # looks like a misregistration: refined there, readings the model explains exactly lost
    # 0.0025 -> 0.028 % and raw12 bursts gained nothing (tests/test_scene.py, docs/method.md)
    refine = opt.refine_frames and opt.aperture == 1
    step = 0
    while True:
        predicted = A.forward(s)
        residual = y - np.tile(a, n_frames) * predicted
        fitted = None if step == 0 and not refine else noise_variance(residual[valid], predicted[valid])
        moved = False
        if refine and step < opt.steps + opt.extra_steps:  # at step 0 against the readings' mean along the warps
            moves, gains = refine_frames(A.forward, s, predicted, a, y, valid, fitted, (h, w), scale=opt.scale,
                                         refine_px=opt.refine_px, refine_exposure=opt.refine_exposure)
            moved = bool(np.any(moves) or np.any(gains != 1))
            if moved:  # sample the scene where the frames now say they see it
                points, exposure, A, valid, y = _moved(points, moves, exposure, gains, frames, good, fine, opt)
                if step == 0:  # ... and start it again there, before s and a take the misregistration up
                    s = _mean_along(A, valid / np.maximum(noise[0], 1e-12), y, valid)
                predicted = A.forward(s)
                residual = y - np.tile(a, n_frames) * predicted
                fitted = None if step == 0 else noise_variance(residual[valid], predicted[valid])
        if step >= opt.steps + (opt.extra_steps if moved else 0):  # a frame that moved adds a step
            break
        if step > 0:
            noise = fitted
        variance = np.maximum(noise[0] + noise[1] * np.abs(predicted), 1e-12)
        weight = valid / variance
        if step > 0 and opt.robust_scale is not None:
            weight /= 1.0 + residual**2 / (opt.robust_scale**2 * variance)
        ds, da, its = _gauss_newton_step(A, gram, weight, residual, predicted, a, s, opt)
        s += ds
        a += da
        iterations += its
        step += 1
    # the prior pulls each a towards 1 by the information of its readings over that plus the prior's;
    # the FPN model shrinks k by its sigma_k, so the pull is taken back here (docs/method.md 8b)
    information = _gain_information(weight, predicted, a.size)
    unpull = np.divide(information + 1.0 / opt.gain_prior**2, information, out=np.ones_like(information),
                       where=information > 0)
    a = 1.0 + (a - 1.0) * unpull
    k = 1.0 / np.where(est & (a > 0), a, 1.0).reshape(h, w)
    est = est.reshape(h, w) & (a.reshape(h, w) > 0)
    k = k / low_pass(k, opt.gauge_sigma, est)  # the gauge: low band exactly 1
    k[~est] = 1.0
    # the noise's own path into a: the same linear step, driven by a draw of the noise model alone
    # (seeded by the tile's place, so that any worker draws the same)
    rng = np.random.default_rng([PROBE_SEED, tile.y0, tile.x0])
    probe = np.where(weight > 0, rng.standard_normal(y.size) * np.sqrt(variance), 0.0)
    ds, da, its = _gauss_newton_step(A, gram, weight, probe, predicted, a, s, opt, priors=False)
    iterations += its
    fitted = probe - np.tile(a, n_frames) * A.forward(ds) - predicted * np.tile(da, n_frames)
    da = da * unpull
    # pixels that read black in some frame: left out there, and their readings kept are biased
    # (a left-out reading, a defect's or a mover's, is not one the solve could have used)
    at_black = frames <= 0
    if tile.excluded is not None:
        at_black &= ~tile.excluded
    at_black = at_black.any(axis=0)
    confidence = _confidence(residual, fitted, probe, da, variance, weight, a, est, n_frames, at_black)
    return k.astype(np.float32), confidence.astype(np.float32), iterations


def _mean_along(A, weight, y, valid):
    """The scene as the weighted mean of the readings that see each sample (the start of a fit)."""
    count = A.back(weight)
    return np.divide(A.back(weight * y), count, out=np.full(count.size, np.mean(y[valid])), where=count > 0)


def _moved(points, moves, exposure, gains, frames, good, fine, opt: SceneOptions):
    """``(points, exposure, A, valid, y)`` of a tile after :func:`refine_frames`' moves and gains."""
    points = [xy + d for xy, d in zip(points, moves)]
    matrix, inside = observation_matrix(points, fine, opt.scale, opt.aperture)
    valid = good.reshape(-1) & inside
    exposure = exposure * gains
    y = np.where(valid, (frames / exposure[:, None, None]).reshape(-1), 0.0)
    return points, exposure, _Sampling(matrix), valid, y


#: Seed of the noise probe of :func:`_solve_tile` (with the tile's origin).
PROBE_SEED = 20261124


def _gain_information(weight, predicted, n: int) -> np.ndarray:
    """Each of the ``n`` pixels' information on its own ``a`` from its readings (the scene taken as
    known): ``sum_t w P^2`` over the frames."""
    return (weight * predicted**2).reshape(-1, n).sum(axis=0)


def _gauss_newton_step(A: "_Sampling", gram, weight, residual, predicted, a, s, opt: SceneOptions, *,
                       priors: bool = True):
    """One Gauss-Newton step ``(ds, da)`` of the weighted squares plus priors, ``a`` eliminated, and
    the conjugate-gradient iterations it took. ``priors=False``: the step's response to ``residual``
    alone (the priors' pull towards their centres left out, their weight kept)."""
    n = a.size
    repeat = residual.size // n
    at = np.tile(a, repeat)
    lam = opt.smoothness * float(np.median(weight[weight > 0]))
    prior = 1.0 / opt.gain_prior**2
    wr = weight * residual
    grad_s = A.back(at * wr) - (lam * (gram @ s) if priors else 0.0)
    grad_a = (predicted * wr).reshape(repeat, n).sum(axis=0) - (prior * (a - 1.0) if priors else 0.0)
    h_aa = _gain_information(weight, predicted, n) + prior
    coupling = weight * at * predicted  # rows of H_sa = A^T diag(w a P), per reading
    data_ss = weight * at**2

    def schur(v):
        u = A.forward(v)
        back = (coupling * u).reshape(repeat, n).sum(axis=0) / h_aa
        return A.back(data_ss * u - coupling * np.tile(back, repeat)) + lam * (gram @ v)

    rhs = grad_s - A.back(coupling * np.tile(grad_a / h_aa, repeat))
    diagonal = A.back_squared(data_ss) + lam * gram.diagonal()
    ds, its = _pcg(schur, rhs, np.maximum(diagonal, 1e-12 * max(diagonal.max(), 1e-300)), opt.cg_iterations,
                   opt.cg_rtol)
    da = (grad_a - (coupling * A.forward(ds)).reshape(repeat, n).sum(axis=0)) / h_aa
    return ds, da, its


class _Sampling:
    """The observation matrix in float32 (the products are most of the solve's time, and bound by
    memory traffic), its transpose and its squared transpose; vectors in and out float64."""

    def __init__(self, matrix):
        self.matrix = matrix.astype(np.float32, copy=False)
        self.transpose = self.matrix.T.tocsr()
        self.squared = self.transpose.copy()
        self.squared.data **= 2

    def forward(self, v):
        return (self.matrix @ v.astype(np.float32)).astype(np.float64)

    def back(self, r):
        return (self.transpose @ r.astype(np.float32)).astype(np.float64)

    def back_squared(self, r):
        """``(A * A)^T r``: the diagonal of ``A^T diag(r) A``."""
        return (self.squared @ r.astype(np.float32)).astype(np.float64)


def _pcg(operator, rhs, diagonal, iterations: int, rtol: float):
    """Jacobi-preconditioned conjugate gradients from 0: the solution and the iterations used."""
    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = r / diagonal
    p = z.copy()
    rz = r @ z
    stop = rtol * np.sqrt(r @ r)
    for i in range(iterations):
        q = operator(p)
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        if np.sqrt(r @ r) <= stop:
            return x, i + 1
        z = r / diagonal
        rz, previous = r @ z, rz
        p = z + (rz / previous) * p
    return x, iterations


def _confidence(residual, fitted, probe, da, variance, weight, a, est, n_frames, at_black) -> np.ndarray:
    """``1 / (1 + (sigma_k / 1 %)^2)`` from the noise probe: ``da`` is how a draw ``probe`` of the
    noise model moves ``a``, ``fitted`` what of it the fit leaves in the readings.

    The probe's ``da^2`` averaged over a 9x9 window is a's variance if the noise model is right;
    it is scaled by the window's residual variance over what the model predicts for the residuals
    (the probe's, which the fit shrinks by the same leverage as the data's), so pixels by features
    the model cannot explain, or readings noisier than the model, report their larger error. A
    window with a pixel that read black in some frame (``at_black``) is not scaled down: the
    readings there that stay above black are the noise's high draws, which a fitted scene explains
    exactly, so their residuals read smaller than the noise (docs/method.md section 8b)."""
    shape = est.shape
    n = est.size
    use = (weight > 0).reshape(n_frames, n)

    def per_pixel(values):
        return np.where(use, values.reshape(n_frames, n), 0.0).sum(axis=0).reshape(shape)

    actual = window_sum(per_pixel(residual**2 / variance), 5)
    expected = window_sum(per_pixel(fitted**2 / variance), 5)
    excess = np.divide(actual, expected, out=np.ones(shape), where=expected > 0)
    excess = np.where(window_sum(at_black.astype(np.float32), 5) > 0, np.maximum(excess, 1.0), excess)
    moved = np.where(est, da.reshape(shape) ** 2, 0.0)
    variance_a = np.divide(window_sum(moved, 9), window_sum(est.astype(np.float64), 9), out=np.full(shape, np.inf),
                           where=est) * excess
    sigma_k = np.sqrt(variance_a) / np.maximum(a.reshape(shape), 1e-3) ** 2
    return np.where(est, confidence_from_sigma(sigma_k), 0.0)
