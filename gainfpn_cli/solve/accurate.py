"""The accurate solver (``solver.method: accurate``): one seamless global
solve that removes what limits the published form (docs/method.md section 5).

Every frame ``s`` anchors comparisons with every other frame ``t``: pixel
``q`` of frame ``s`` sees the scene point that frame ``t`` sees at
``M_st q`` (``M_st = H_t H_s^-1`` for global motion, a map for a field
model: :mod:`geometry.warps`), so brightness constancy of the corrected frames
reads

    k(q) i_s(q)  =  sum_c w_c k(c) i_t(c)                              (*)

where the right side interpolates the *corrected* frame ``t`` with a
high-order kernel (Lanczos-4 by default). Anchoring all frames, not only the
reference, averages the temporal noise of each pixel's own readings instead
of copying frame 0's noise into ``k``.

For each pixel, the least-squares ``k(q)`` given the right sides is
``(M k)(q) = sum_{s,t} v i_s W_st(k i_t) / sum_{s,t} v i_s^2`` (``v``: the
comparison is valid). The estimate is the fixed point ``k = M k``. Writing
``k = 1 + x``, it solves ``(I - M + mu G) x = M 1 - 1`` by GMRES, where ``G``
is a Gaussian low-pass: the low spatial frequencies that small motion cannot
observe (docs/method.md section 5.3) get a penalty that keeps the system well
conditioned, and the final gauge divides ``k`` by its own low-pass, so the
low band is 1 by construction and the mean is 1.

The frame is cut into overlapping tiles, solved independently (in parallel)
and blended with linear ramps in the overlaps. The tiling depends only on
the frame size and ``tile``, so results are bit-identical for any number of
workers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import EstimationError
from ..geometry.resample import KERNELS, bounded, low_pass, sample, valid_samples, window_sum
from ..metrics import MAD_TO_SIGMA
from .phase import phase_weighted
from .result import AccurateStats, GainResult, confidence_from_sigma
from .tiling import Tile, blend, checked_problem, solve_tiles, tiles_of


@dataclass(frozen=True)
class AccurateOptions:
    """Options of the accurate solver.

    Attributes
    ----------
    kernel : {"lanczos4", "cubic", "bilinear"}
        Interpolation of the corrected frames along trajectories.
    anchors : {"all", "reference"}
        Which frames anchor comparisons: every frame (noise of each pixel's
        own readings averaged) or only the reference (as the paper).
    partners : int
        Frames each anchor is compared with, nearest in burst order first
        (next, previous, second next, ...); 0 for every other frame. Each
        pair costs one warp per solver iteration: 2 partners of 8 frames
        cost 2/7 of all (measured, 480x640: 19.1x against 20.4x MSE
        reduction, in half the time).
    gauge_sigma : float
        Gaussian sigma (px) of the low band that is gauged to 1.
    mu : float
        Weight of the low-band penalty in the solve.
    rtol : float
        GMRES relative tolerance. Measured on three 240x320 bursts: 1e-3
        gives the MSE reduction of 1e-5 within 1.5 % in 45 % less time;
        1e-2 loses 0.5-2 % and saves another 30 %.
    maxiter : int
        GMRES restarts at most (each of up to 50 iterations). One: stopping
        early regularises, as the solve is ill-posed where few comparisons
        pin k down (the iterations past ~50 fit noise into those modes).
        Bursts of 8 frames converge in 10-25 iterations and are unaffected;
        measured with 10 -> 1 (balanced, one run each): 5 frames of 2 MP,
        3.3x in 45 s -> 4.9x in 15 s; 4 frames of 2 MP, rejected by the
        hold-out after 79 s -> 1.5x in 11 s (the bench); a 12-bit RGGB DNG burst
        of 6 MP x 8, whose red and blue planes took a median 140 and up to
        975 iterations, 1.36x in 128 s -> 1.38x in 55 s.
    tile : int
        Side of the tiles' cores (px); halo of ``halo`` px around each.
    halo : int
    robust_rounds : int
        Re-solves with Cauchy weights ``1 / (1 + (r / (c s))^2)`` on the
        residuals ``r`` of (*) (``s``: their robust spread, ``c``:
        ``robust_scale``), which discount comparisons that interpolation
        cannot predict (aliased edges) or that do not follow the motion.
    robust_scale : float
    gain_range : (float, float)
        Gains outside it are not physical: those pixels are left unestimated
        (k = 1, confidence 0) and counted.
    """

    kernel: str = "lanczos4"
    anchors: str = "all"
    partners: int = 0
    gauge_sigma: float = 8.0
    mu: float = 1.0
    rtol: float = 1e-3
    maxiter: int = 1
    tile: int = 512
    halo: int = 24
    robust_rounds: int = 2
    robust_scale: float = 3.0
    phase_weights: bool = False
    gain_range: tuple[float, float] = (0.5, 2.0)


def solve_accurate(
    frames: np.ndarray,
    motion,
    *,
    options: AccurateOptions = AccurateOptions(),
    saturation: float | None = None,
    excluded: np.ndarray | None = None,
    exposures=None,
    workers: int = 2,
    progress=None,
    executor=None,
) -> GainResult:
    """Estimate ``k`` for a burst whose motion is known.

    Parameters
    ----------
    frames : ndarray, shape (F, H, W)
        All frames, DN after offset removal; ``F >= 2``.
    motion : GlobalWarp, FieldWarp or ndarray of shape (F, 3, 3)
        The motion, or ``H_t_ref`` of each frame (the reference's is the identity).
    saturation : float, optional
        Samples at or above this level are excluded.
    excluded : ndarray of bool, shape (F, H, W), optional
        Samples to leave out as well (a moving object's, which follow no motion).
    exposures : sequence of float, optional
        Each frame's exposure relative to the reference (:mod:`exposure`):
        frames are compared divided by it. None: all exposed alike.
    workers : int
        Local processes that solve the tiles (the tiling depends only on the frame size and
        ``options.tile``, so the result does not depend on it).
    executor : parallel.DaskExecutor, optional
        Solve the tiles there instead.
    """
    return solve_accurate_many([dict(frames=frames, motion=motion, saturation=saturation, excluded=excluded,
                                     exposures=exposures)], options=options, workers=workers, progress=progress,
                               executor=executor)[0]


def solve_accurate_many(problems, *, options: AccurateOptions = AccurateOptions(), workers: int = 2, progress=None,
                        executor=None) -> list[GainResult]:
    """:func:`solve_accurate` of each of ``problems`` (dicts of its ``frames``, ``motion`` and, as
    wanted, ``saturation``, ``excluded`` and ``exposures``), their tiles solved in one go: problems
    of one tile each still run on every worker. The same results as one call each."""
    prepared = [_prepare(p["frames"], p["motion"], options, p.get("saturation"), p.get("excluded"),
                         p.get("exposures")) for p in problems]
    shapes = iter([np.shape(p["frames"])[1:] for p in problems])
    return solve_tiles(prepared, _solve_tile, lambda tiles, results: _assemble(tiles, results, next(shapes), options),
                       workers=workers, progress=progress, executor=executor)


def _prepare(frames, motion, options: AccurateOptions, saturation, excluded, exposures) -> list:
    """The tiles of one problem, its inputs checked (see :func:`solve_accurate`)."""
    if options.kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {options.kernel!r}")
    if options.anchors not in ("all", "reference"):
        raise ValueError(f"anchors must be 'all' or 'reference', got {options.anchors!r}")
    frames, motion, exposures = checked_problem(frames, motion, excluded, exposures)
    h, w = frames.shape[1:]
    radius = KERNELS[options.kernel][1]
    if min(h, w) <= 2 * radius:
        raise EstimationError(
            f"frames of {w}x{h} px are too small for the {options.kernel} kernel, which needs more than "
            f"{2 * radius} px on each side (use solver.interpolation: bilinear, or solver.method: paper)"
        )
    pairs = comparison_pairs(frames.shape[0], options)
    return tiles_of(frames, excluded, motion, saturation, options, exposures, pairs)


def _assemble(tiles, results, shape, options: AccurateOptions) -> GainResult:
    """The tiles' k and confidence blended into one gauged plane (:func:`tiling.blend`)."""
    b = blend([(t.y0, t.x0) for t in tiles], results, shape, halo=options.halo, gain_range=options.gain_range)
    stats = AccurateStats(tiles=len(tiles), gmres_iterations=b.iterations, unestimated_pixels=b.unestimated_pixels,
                          out_of_range_pixels=b.out_of_range_pixels, median_confidence=b.median_confidence)
    return GainResult(b.k, b.confidence, stats)


def comparison_pairs(n: int, options: AccurateOptions) -> tuple:
    """The (anchor, partner) frames the solver compares among ``n`` frames (``options.anchors``,
    ``options.partners``)."""
    anchors = range(n) if options.anchors == "all" else [0]
    return tuple((s, t) for s in anchors for t in partner_frames(s, n, options.partners))


def partner_frames(s: int, n: int, count: int) -> list[int]:
    """The ``count`` frames nearest to ``s`` in burst order (next, previous, ...); all others if 0."""
    order = []
    for d in range(1, n):
        for t in ((s + d) % n, (s - d) % n):
            if t != s and t not in order:
                order.append(t)
    return order if count <= 0 else order[:count]


def _solve_tile(tile: Tile) -> tuple[np.ndarray, np.ndarray, int]:
    """k, confidence and GMRES iterations for one tile (its halo included)."""
    opt = tile.options
    frames, good = tile.readings()
    shape = frames.shape[1:]
    region = (tile.y0, tile.x0) + shape
    # (s, t, M_st in tile pixels); a map is used every iteration: bounded once
    pair_maps = [(s, t, bounded(tile.motion.pair(s, t, region), shape)) for s, t in tile.pairs]
    valid = [valid_samples(good[t], M, shape, kernel=opt.kernel) & good[s] for s, t, M in pair_maps]
    weights = [v.astype(np.float64) for v in valid]
    x = np.zeros(shape)
    iterations = 0
    for round_ in range(opt.robust_rounds + 1):
        denom = sum(wt * frames[s] ** 2 for (s, _), wt in zip(tile.pairs, weights))
        est = denom > 0
        if not est.any():
            return np.ones(shape), np.zeros(shape), iterations
        x, its = _gmres_round(frames, pair_maps, opt, weights, denom, est, x)
        iterations += its
        k = 1.0 + x
        residuals = _residuals(k, frames, pair_maps, opt.kernel)
        if round_ < opt.robust_rounds:
            spread = MAD_TO_SIGMA * np.median(np.abs(np.concatenate([r[v & est] for r, v in zip(residuals, valid)])))
            scale = opt.robust_scale * max(spread, 1e-12)
            weights = [v / (1.0 + (r / scale) ** 2) for r, v in zip(residuals, valid)]
            if opt.phase_weights:
                weights = phase_weighted(weights, residuals, valid, pair_maps, shape)
    k = k / low_pass(k, opt.gauge_sigma, est)  # the gauge: low band exactly 1
    k[~est] = 1.0
    fractions = _fit_fractions(tile.pairs, valid, shape) if opt.anchors == "all" else None
    confidence = _confidence(residuals, weights, valid, _anchor_information(frames, tile.pairs, weights), est,
                             fractions)
    return k.astype(np.float32), confidence.astype(np.float32), iterations


def _anchor_information(frames, pairs, weights) -> np.ndarray:
    """``sum_s a_s(q) i_s(q)^2``, ``a_s`` the weighted fraction of frame s's comparisons that count.

    The comparisons anchored on one reading ``i_s(q)`` share its noise, so k
    learns from each reading once, not once per partner frame.
    """
    shape = frames.shape[1:]
    partners: dict[int, int] = {}
    for s, _ in pairs:
        partners[s] = partners.get(s, 0) + 1
    info = np.zeros(shape)
    for (s, _), wt in zip(pairs, weights):
        info += wt / partners[s] * frames[s] ** 2
    return info


def _gmres_round(frames, pair_maps, opt, weights, denom, est, x0) -> tuple[np.ndarray, int]:
    """Solve ``(I - M + mu G) x = M 1 - 1`` for one set of comparison weights."""
    from scipy.sparse.linalg import LinearOperator, gmres

    shape = frames.shape[1:]

    anchors = [wt * frames[s] for (s, _, _), wt in zip(pair_maps, weights)]
    frames32 = {t: frames[t].astype(np.float32) for _, t, _ in pair_maps}

    def apply_m(k: np.ndarray) -> np.ndarray:
        k32 = k.astype(np.float32)
        corrected = {t: k32 * f for t, f in frames32.items()}  # each frame once, not once per pair
        num = np.zeros(shape)
        for (_, t, M), anchor in zip(pair_maps, anchors):
            num += anchor * sample(corrected[t], M, shape, kernel=opt.kernel)
        return np.divide(num, denom, out=np.zeros(shape), where=est)

    def operator(xv: np.ndarray) -> np.ndarray:
        x = xv.reshape(shape)
        y = x - apply_m(x) + opt.mu * low_pass(x, opt.gauge_sigma)
        y[~est] = x[~est]
        return y.ravel()

    rhs = apply_m(np.ones(shape)) - 1.0
    rhs[~est] = 0.0
    count = [0]
    size = rhs.size
    x, _ = gmres(LinearOperator((size, size), matvec=operator, dtype=float), rhs.ravel(), x0=x0.ravel(),
                 rtol=opt.rtol, restart=50, maxiter=opt.maxiter,
                 callback=lambda _: count.__setitem__(0, count[0] + 1), callback_type="pr_norm")
    return x.reshape(shape), count[0]


def _residuals(k: np.ndarray, frames: np.ndarray, pair_maps, kernel: str) -> list[np.ndarray]:
    """Residual of (*) for every comparison: ``k i_s - W_st(k i_t)``."""
    return [k * frames[s] - sample(k * frames[t], M, k.shape, kernel=kernel) for s, t, M in pair_maps]


def _fit_fractions(pairs, valid, shape) -> tuple[np.ndarray, np.ndarray]:
    """What the fit takes of each pixel's readings (docs/method.md section 8, "sigma_k"): the
    fraction ``rho`` of a residual's variance that survives the fit, ``1 - 1 / T - m``, and the
    fraction ``1 - m`` of a reading's information that k keeps.

    ``T(q)``: the readings of pixel ``q`` that anchor a valid comparison (each takes ``1 / T`` of
    their residuals into k); ``m(q)``: the mean over them of ``1 / (1 + n_s)``, ``n_s`` the valid
    comparisons anchored on reading ``s`` (the partners' readings take that share as the scene
    point's own value). Every frame compared with every other gives ``1 - 2 / T`` and ``1 - 1 / T``.
    """
    partners = {}
    for (s, _), v in zip(pairs, valid):
        partners[s] = partners.get(s, 0) + v.astype(np.int32)
    anchors = np.zeros(shape)
    scene_share = np.zeros(shape)
    for count in partners.values():
        anchors += count > 0
        scene_share += np.where(count > 0, 1.0 / (1.0 + count), 0.0)
    seen = anchors > 0
    m = np.divide(scene_share, anchors, out=np.ones(shape), where=seen)
    rho = np.where(seen, 1.0 - np.divide(1.0, anchors, out=np.ones(shape), where=seen) - m, 0.0)
    return np.maximum(rho, 0.0), 1.0 - m


#: Smallest residual fraction :func:`_confidence` divides by: that of 3 frames each compared with the
#: others (``1 - 2 / 3``), the fewest a burst is fitted on. Where fewer readings see a pixel's
#: neighbourhood (a frame's border, readings near black or clipped), the window's residuals are too few
#: to say more, and dividing by their smaller fraction made the highest tenth of sigma_k 8x too large
#: (dark dead-leaves burst of 4 frames: RMS error 0.13x the RMS sigma_k there).
MIN_RHO = 1.0 / 3.0


def _confidence(residuals, weights, valid, information, est, fractions=None) -> np.ndarray:
    """``1 / (1 + (sigma_k / 1 %)^2)`` with ``sigma_k`` the predicted standard error of k.

    ``sigma_k(q)^2 = v(q) / (2 rho(q) (1 - m(q)) sum_s a_s i_s(q)^2)``: ``v(q)`` is the weighted
    variance of the residuals of (*) in a 5x5 window around ``q`` (local, so that pixels next to
    features interpolation cannot follow report their larger uncertainty); a residual holds the
    anchor's noise and about as much again from the prediction, hence the 2; the sum counts each
    reading once (:func:`_anchor_information`). The residuals are what the fit left: ``rho`` (the
    window's mean, weighted as ``v``) restores the variance the fit took, and ``1 - m`` the
    information k lost to the scene (``fractions``, :func:`_fit_fractions`; docs/method.md section 8
    gives what they predict against k's measured error). Without ``fractions`` (only the reference
    anchors) both are 1.
    """
    shape = information.shape
    squares = np.zeros(shape)
    counts = np.zeros(shape)
    for r, wt, v in zip(residuals, weights, valid):
        use = v & est
        squares += np.where(use, wt * r**2, 0.0)
        counts += np.where(use, wt, 0.0)
    box = lambda a: window_sum(a, 5)  # noqa: E731
    boxed = box(counts)
    local = np.divide(box(squares), boxed, out=np.full(shape, np.inf), where=boxed > 0)
    kept = 1.0
    if fractions is not None:
        rho, kept = fractions
        rho_local = np.divide(box(rho * counts), boxed, out=np.zeros(shape), where=boxed > 0)
        local = local / np.maximum(rho_local, MIN_RHO)
    sigma_k = np.sqrt(np.divide(local, 2.0 * information * kept, out=np.full(shape, np.inf),
                                where=est & (information * kept > 0)))
    return np.where(est, confidence_from_sigma(sigma_k), 0.0)
