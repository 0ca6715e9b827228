"""The scene model of the scene solver (docs/method.md section 8b): the noise model and the fit of
the scene ``S`` and the gains ``a`` to a tile's readings by Gauss-Newton (:func:`fit_tile`), through
the sampling operator ``B W_t`` of :mod:`solve.sampling`.

:mod:`solve.scene` turns a fit into k and its confidence; :mod:`solve.bootstrap` renders the burst a
fit predicts. Pure array functions on one tile at a time.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..geometry.resample import positions
from .frames import refine_frames, rms_move
from .sampling import _U1, Sampling, compiled, sampling
from .tiling import Tile

#: Median of a chi-square variable of one degree of freedom: a median of squared normal
#: residuals over it is their variance.
CHI2_MEDIAN = 0.4549364


def add_smoothness(v: np.ndarray, fine: tuple[int, int], weight: float, out: np.ndarray) -> np.ndarray:
    """``out + weight * D^T D v``, ``D`` the forward differences of the ``fine`` grid along both axes."""
    _add_smoothness(np.asarray(v, np.float64), fine[0], fine[1], float(weight), out)
    return out


def smoothness_diagonal(fine: tuple[int, int]) -> np.ndarray:
    """The diagonal of ``D^T D``: each sample's number of neighbours on the ``fine`` grid."""

    def along(n):
        at = np.arange(n)
        return (at > 0).astype(np.float64) + (at < n - 1)

    return (along(fine[0])[:, None] + along(fine[1])[None, :]).reshape(-1)


@compiled
def _add_smoothness(v, fh, fw, weight, out):
    # unsigned indices, as solve/sampling.py's loops: 0.37 -> 0.22 ms on the 576 px grid of python
    # docs/bench/sampling.py, the same bits
    i, row = np.uint64(0), np.uint64(fw)
    for y in range(fh):
        for x in range(fw):
            change = 0.0
            if x > 0:
                change += v[i] - v[i - _U1]
            if x < fw - 1:
                change += v[i] - v[i + _U1]
            if y > 0:
                change += v[i] - v[i - row]
            if y < fh - 1:
                change += v[i] - v[i + row]
            out[i] += weight * change
            i += _U1


#: Levels the noise model's bin edges are the quantiles of (every m-th of a tile's readings, m the
#: readings over this); its medians take every reading. Sorting all of a tile's ~480 000 levels for
#: the edges took 23-25 ms of the model's 34-37 ms (17 ms without), four times a tile's fit.
EDGE_SAMPLES = 1 << 15


def noise_variance(residuals: np.ndarray, predicted: np.ndarray, bins: int = 8) -> tuple[float, float]:
    """``(alpha, beta)`` of the noise model ``var = alpha + beta * predicted`` (shot and read
    noise), fitted to the squared ``residuals`` by robust medians over bins of the level (quantile
    bins of up to :data:`EDGE_SAMPLES` levels evenly spaced in the readings' order)."""
    levels = np.asarray(predicted, np.float64)
    edges = np.quantile(levels[:: max(1, levels.size // EDGE_SAMPLES)], np.linspace(0, 1, bins + 1))
    # bin b holds the levels in [edges[b], edges[b + 1]) (the first all below, the last all above), its
    # levels and squares gathered into one slice of each in one pass
    by_level, squares = np.empty(levels.size), np.empty(levels.size)
    counts = _by_bin(np.asarray(residuals, np.float64), levels, edges, by_level, squares)
    bounds = np.concatenate([[0], np.cumsum(counts)])
    level, variance = [], []
    for lo, hi in pairwise(bounds):
        if hi - lo >= 8:
            level.append(np.median(by_level[lo:hi], overwrite_input=True))
            variance.append(np.median(squares[lo:hi], overwrite_input=True) / CHI2_MEDIAN)
    if len(level) < 2 or np.ptp(level) <= 0:
        return float(np.mean(variance)) if variance else 1.0, 0.0
    beta, alpha = np.polyfit(level, variance, 1)
    if beta < 0 or alpha < 0:  # a negative term is noise in the fit: the other carries it
        beta = max(beta, 0.0)
        alpha = max(float(np.median(np.array(variance) - beta * np.array(level))), 0.0)
    return float(alpha), float(beta)


@compiled
def _by_bin(residuals, levels, edges, by_level, squares):
    """Each level and its residual's square into ``by_level`` and ``squares``, bin by bin (the bin of
    a level: the last of ``edges[1:-1]`` at or below it, else the first), in the readings' order
    within a bin; returns the bins' counts."""
    last = edges.size - 2
    which = np.empty(levels.size, np.int8)
    counts = np.zeros(last + 1, np.int64)
    for i in range(levels.size):
        b = last
        while b > 0 and levels[i] < edges[b]:
            b -= 1
        which[i] = b
        counts[b] += 1
    fill = np.zeros(last + 1, np.int64)
    for b in range(1, last + 1):
        fill[b] = fill[b - 1] + counts[b - 1]
    for i in range(levels.size):
        b = which[i]
        by_level[fill[b]] = levels[i]
        squares[fill[b]] = residuals[i] * residuals[i]
        fill[b] += 1
    return counts


@dataclass(frozen=True)
class SceneFit:
    """One tile's fitted model (:func:`fit_tile`): the readings ``y`` (divided by the frames' unit
    and exposures) and where they count, the model's prediction of them without the gains
    (``B W_t S``), the gains ``a``, the last step's weights, variances and residuals, the fitted
    noise model ``(alpha, beta)`` (None if the fit never measured one), each frame's exposure
    relative to the readings', the sampling operator, the CG iterations and where each frame's
    pixels see the first frame's grid, as refined against the model (``(pixels, 2)`` (x, y) per
    frame, tile px): the registration the fit used, plus any significant move below materiality
    that the refinement after its last step found (reported, not fitted); and the last step's
    smoothness weight, which the solves that calibrate the fit's confidence take up."""

    y: np.ndarray
    valid: np.ndarray
    predicted: np.ndarray
    a: np.ndarray
    s: np.ndarray
    weight: np.ndarray
    variance: np.ndarray
    residual: np.ndarray
    noise: tuple | None
    exposure: np.ndarray
    est: np.ndarray
    A: Sampling
    iterations: int
    points: list
    lam: float  # the last step's smoothness weight (smoothness_weight of its weights)


def fit_tile(tile: Tile) -> SceneFit | None:
    """The scene model fitted to one tile (its halo included); None if no pixel is seen twice."""
    opt = tile.options
    frames, good = tile.readings()
    n_frames, h, w = frames.shape
    region = (tile.y0, tile.x0, h, w)
    fine = (opt.scale * h, opt.scale * w)
    points = [positions(tile.motion.pair(t, 0, region), (h, w)).reshape(-1, 2) for t in range(n_frames)]
    A, inside = sampling(points, fine, opt.scale, opt.aperture)
    valid = good.reshape(-1) & inside
    y = np.where(valid, frames.reshape(-1), 0.0)
    seen = valid.reshape(n_frames, -1).sum(axis=0)
    est = seen >= 2  # one reading: a would explain it alone
    if not est.any():
        return None

    s = _mean_along(A, valid.astype(np.float64), y, valid)
    a = np.ones(h * w)
    iterations = 0
    uniform = (np.var(y[valid]) * 1e-4, 0.0)  # the first step: uniform weights
    noise = uniform
    exposure = np.ones(n_frames)
    # a plane sampled every other photosite (aperture below 1) is aliased enough that its misfit
    # looks like a misregistration: refined there, readings the model explains exactly lost
    # 0.0025 -> 0.028 % and raw12 bursts gained nothing (tests/test_scene.py, docs/method.md)
    refine = opt.refine_frames and not opt.colour_plane
    step, first_moves, restarted = 0, None, False
    while True:
        small = None  # this round's significant moves below materiality, after the last step
        predicted = A.forward(s)
        residual = y - np.tile(a, n_frames) * predicted
        fitted = None if step == 0 and not refine else noise_variance(residual[valid], predicted[valid])
        moved = False
        if refine and step < opt.steps + opt.extra_steps and not (step == 0 and restarted):
            # before a step that follows anyway any significant change is taken, after the last
            # only a material one, which adds a step
            material = step == 0 or step >= opt.steps
            moves, gains, kept = refine_frames(A.forward, s, predicted, a, y, valid, fitted, (h, w), scale=opt.scale,
                                               refine_px=opt.refine_px if material else 0.0,
                                               refine_exposure=opt.refine_exposure if material else 0.0)
            if opt.refine_warps == "shift":  # each frame's mean move (fitted with the field's shape, dropped)
                moves = np.broadcast_to(moves.mean(axis=1, keepdims=True), moves.shape).copy()
            if step >= opt.steps:  # reported below if no step follows
                small = np.where(kept[:, None, None], 0.0, moves)
            moves, gains = np.where(kept[:, None, None], moves, 0.0), np.where(kept, gains, 1.0)
            if step == 0:
                # against the readings' mean along the warps (a = 1 leaves the FPN in them) the
                # warps moved by 0.1-0.4 px where they were 0.02-0.05 px off: their change waits
                # for the fitted model to confirm a material misregistration
                first_moves, moves = moves, np.zeros_like(moves)
            elif step == 1 and not restarted and np.any(first_moves) and _material(moves, opt.refine_px):
                # confirmed: start again with the first moves, before s and a take it up
                points, exposure, A, valid, y = _moved(points, first_moves, exposure, np.ones(n_frames), frames,
                                                       good, fine, opt)
                s = _mean_along(A, valid / np.maximum(uniform[0], 1e-12), y, valid)
                a = np.ones(h * w)
                noise, step, restarted = uniform, 0, True
                continue
            moved = bool(np.any(moves) or np.any(gains != 1))
            if moved:  # sample the scene where the frames now say they see it
                points, exposure, A, valid, y = _moved(points, moves, exposure, gains, frames, good, fine, opt)
                if step == 0:  # ... and start it again there, before s and a take the misregistration up
                    s = _mean_along(A, valid / np.maximum(noise[0], 1e-12), y, valid)
                predicted = A.forward(s)
                residual = y - np.tile(a, n_frames) * predicted
                fitted = None if step == 0 else noise_variance(residual[valid], predicted[valid])
            moved = moved and material
        if step >= opt.steps + (opt.extra_steps if moved else 0):  # a frame that moved adds a step
            if small is not None and not moved:
                # a significant move below materiality after the last step refines the warps the fit
                # reports, not the fit: moved against a scene that has taken up part of the
                # misregistration, with each gain refitted and the scene held, k lost 10 % of its MSE
                # ratio under 1 px of distortion with a homography forced (bench group motion_model)
                points = [xy + d for xy, d in zip(points, small)]
            break
        if step > 0:
            noise = fitted
        variance = np.maximum(noise[0] + noise[1] * np.abs(predicted), 1e-12)
        weight = valid / variance
        if step > 0 and opt.robust_scale is not None:
            weight /= 1.0 + residual**2 / (opt.robust_scale**2 * variance)
        lam = smoothness_weight(weight, opt)
        ds, da, its = gauss_newton_step(A, weight, residual, predicted, a, s, opt, lam=lam)
        s += ds
        a += da
        iterations += its
        step += 1
    return SceneFit(y, valid, predicted, a, s, weight, variance, residual, fitted, exposure, est, A, iterations,
                    points, lam)



def _mean_along(A, weight, y, valid):
    """The scene as the weighted mean of the readings that see each sample (the start of a fit)."""
    count = A.back(weight)
    return np.divide(A.back(weight * y), count, out=np.full(count.size, np.mean(y[valid])), where=count > 0)


def _material(moves: np.ndarray, refine_px: float) -> bool:
    """Whether some frame's ``moves`` ``(frames, pixels, 2)`` are more than ``refine_px`` RMS."""
    return bool(np.any(rms_move(moves) > refine_px))


def _moved(points, moves, exposure, gains, frames, good, fine, opt):
    """``(points, exposure, A, valid, y)`` of a tile after :func:`refine_frames`' moves and gains."""
    points = [xy + d for xy, d in zip(points, moves)]
    A, inside = sampling(points, fine, opt.scale, opt.aperture)
    valid = good.reshape(-1) & inside
    exposure = exposure * gains
    y = np.where(valid, (frames / exposure[:, None, None]).reshape(-1), 0.0)
    return points, exposure, A, valid, y



def gain_information(weight, predicted, n: int) -> np.ndarray:
    """Each of the ``n`` pixels' information on its own ``a`` from its readings (the scene taken as
    known): ``sum_t w P^2`` over the frames."""
    return (weight * predicted**2).reshape(-1, n).sum(axis=0)


def smoothness_weight(weight, opt) -> float:
    """The weight of the scene's squared gradient in a step with reading ``weight``s: ``opt.smoothness``
    times the median positive one's."""
    return opt.smoothness * float(np.median(weight[weight > 0]))


def gauss_newton_step(A: Sampling, weight, residual, predicted, a, s, opt, *, priors: bool = True,
                      iterations: int | None = None, lam: float | None = None):
    """One Gauss-Newton step ``(ds, da)`` of the weighted squares plus priors, ``a`` eliminated, and
    the conjugate-gradient iterations it took. ``priors=False``: the step's response to ``residual``
    alone (the priors' pull towards their centres left out, their weight kept). ``iterations``:
    the conjugate-gradient cap if not ``opt.cg_iterations``; ``lam``: :func:`smoothness_weight` of
    ``weight`` if already known."""
    steps, its = gauss_newton_path(A, weight, residual, predicted, a, s, opt, priors=priors,
                                   stops=(opt.cg_iterations if iterations is None else iterations,), lam=lam)
    ds, da, _ = steps[-1]
    return ds, da, its


def gauss_newton_path(A: Sampling, weight, residual, predicted, a, s, opt, *, priors: bool, stops: tuple[int, ...],
                      lam: float | None = None):
    """:func:`gauss_newton_step` as its conjugate gradients go: the step ``(ds, da, A ds)`` (the last:
    the change of the readings' scene) after each of ``stops`` iterations (increasing; the last is the
    cap, and a solve that converged before a stop gives its final step there), and the iterations
    taken."""
    n = a.size
    repeat = residual.size // n
    at = np.tile(a, repeat)
    lam = smoothness_weight(weight, opt) if lam is None else lam
    prior = 1.0 / opt.gain_prior**2
    wr = weight * residual
    grad_s = A.back(at * wr)
    if priors:
        add_smoothness(s, A.fine, -lam, grad_s)
    grad_a = (predicted * wr).reshape(repeat, n).sum(axis=0) - (prior * (a - 1.0) if priors else 0.0)
    inverse_haa = 1.0 / (gain_information(weight, predicted, n) + prior)
    coupling = weight * at * predicted  # rows of H_sa = A^T diag(w a P), per reading
    data_ss = weight * at**2
    u, z = np.empty(residual.size), np.empty(residual.size)

    def schur(v):
        A.forward(v, u)
        _eliminated(u, coupling, data_ss, inverse_haa, z)
        return add_smoothness(v, A.fine, lam, A.back(z))

    rhs = A.back(-coupling * np.tile(grad_a * inverse_haa, repeat), grad_s)
    diagonal = A.back_squared(data_ss) + lam * smoothness_diagonal(A.fine)
    path, its = _pcg_path(schur, rhs, np.maximum(diagonal, 1e-12 * max(diagonal.max(), 1e-300)), stops,
                          opt.cg_rtol)
    steps = []
    for ds in path:
        seen = A.forward(ds)
        steps.append((ds, (grad_a - (coupling * seen).reshape(repeat, n).sum(axis=0)) * inverse_haa, seen))
    return steps, its


@compiled
def _eliminated(u, coupling, data_ss, inverse_haa, z):
    """``z = D u - c (c^T u) / h`` per pixel: the readings' part of the Schur complement's product,
    ``a`` eliminated (``c``: the coupling, ``D``: the scene's data weights, ``h``: a's information;
    readings frame-major)."""
    n = inverse_haa.size
    n_frames = u.size // n
    shared = np.zeros(n)
    for t in range(n_frames):
        for p in range(n):
            shared[p] += coupling[t * n + p] * u[t * n + p]
    for p in range(n):
        shared[p] *= inverse_haa[p]
    for t in range(n_frames):
        for p in range(n):
            i = t * n + p
            z[i] = data_ss[i] * u[i] - coupling[i] * shared[p]


def _pcg_path(operator, rhs, diagonal, stops: tuple[int, ...], rtol: float):
    """Jacobi-preconditioned conjugate gradients from 0, up to ``stops[-1]`` iterations: the iterate
    after each of ``stops`` (the final one for those after it converged) and the iterations used."""
    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = r / diagonal
    p = z.copy()
    rz = r @ z
    stop = rtol * np.sqrt(r @ r)
    path = []
    for i in range(stops[-1]):
        q = operator(p)
        rr, rz_next = _cg_update(rz / (p @ q), p, q, diagonal, x, r, z)
        if np.sqrt(rr) <= stop:
            return path + [x] * (len(stops) - len(path)), i + 1
        path.extend(x.copy() for _ in range(stops[:-1].count(i + 1)))
        _cg_direction(z, rz_next / rz, p)
        rz = rz_next
    return path + [x] * (len(stops) - len(path)), stops[-1]


@compiled
def _cg_update(alpha, p, q, diagonal, x, r, z):
    """One conjugate-gradient update in one pass: ``x += alpha p``, ``r -= alpha q``, ``z = r / diagonal``;
    returns ``r . r`` and ``r . z``."""
    rr = 0.0
    rz = 0.0
    for i in range(x.size):
        x[i] += alpha * p[i]
        r[i] -= alpha * q[i]
        z[i] = r[i] / diagonal[i]
        rr += r[i] * r[i]
        rz += r[i] * z[i]
    return rr, rz


@compiled
def _cg_direction(z, beta, p):
    """``p = z + beta p``."""
    for i in range(p.size):
        p[i] = z[i] + beta * p[i]
