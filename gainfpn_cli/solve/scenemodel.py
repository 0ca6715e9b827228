"""The scene model of the scene solver (docs/method.md section 8b): the sampling matrix ``B W_t`` of a
tile's readings from a latent scene finer than its pixels, the noise model, and the fit of the scene
``S`` and the gains ``a`` to the readings by Gauss-Newton (:func:`fit_tile`).

:mod:`solve.scene` turns a fit into k and its confidence; :mod:`solve.bootstrap` renders the burst a
fit predicts. Pure array functions on one tile at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.resample import positions
from .frames import refine_frames
from .tiling import Tile

#: Median of a chi-square variable of one degree of freedom: a median of squared normal
#: residuals over it is their variance.
CHI2_MEDIAN = 0.4549364


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


@dataclass(frozen=True)
class SceneFit:
    """One tile's fitted model (:func:`fit_tile`): the readings ``y`` (divided by the frames' unit
    and exposures) and where they count, the model's prediction of them without the gains
    (``B W_t S``), the gains ``a``, the last step's weights, variances and residuals, the fitted
    noise model ``(alpha, beta)`` (None if the fit never measured one), each frame's exposure
    relative to the readings', the last Gauss-Newton step's operands and the CG iterations."""

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
    A: object
    gram: object
    iterations: int


def fit_tile(tile: Tile) -> SceneFit | None:
    """The scene model fitted to one tile (its halo included); None if no pixel is seen twice."""
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
        return None

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
        ds, da, its = gauss_newton_step(A, gram, weight, residual, predicted, a, s, opt)
        s += ds
        a += da
        iterations += its
        step += 1
    return SceneFit(y, valid, predicted, a, s, weight, variance, residual, fitted, exposure, est, A, gram, iterations)



def _mean_along(A, weight, y, valid):
    """The scene as the weighted mean of the readings that see each sample (the start of a fit)."""
    count = A.back(weight)
    return np.divide(A.back(weight * y), count, out=np.full(count.size, np.mean(y[valid])), where=count > 0)


def _moved(points, moves, exposure, gains, frames, good, fine, opt):
    """``(points, exposure, A, valid, y)`` of a tile after :func:`refine_frames`' moves and gains."""
    points = [xy + d for xy, d in zip(points, moves)]
    matrix, inside = observation_matrix(points, fine, opt.scale, opt.aperture)
    valid = good.reshape(-1) & inside
    exposure = exposure * gains
    y = np.where(valid, (frames / exposure[:, None, None]).reshape(-1), 0.0)
    return points, exposure, _Sampling(matrix), valid, y



def gain_information(weight, predicted, n: int) -> np.ndarray:
    """Each of the ``n`` pixels' information on its own ``a`` from its readings (the scene taken as
    known): ``sum_t w P^2`` over the frames."""
    return (weight * predicted**2).reshape(-1, n).sum(axis=0)


def gauss_newton_step(A: _Sampling, gram, weight, residual, predicted, a, s, opt, *,
                       priors: bool = True, iterations: int | None = None):
    """One Gauss-Newton step ``(ds, da)`` of the weighted squares plus priors, ``a`` eliminated, and
    the conjugate-gradient iterations it took. ``priors=False``: the step's response to ``residual``
    alone (the priors' pull towards their centres left out, their weight kept). ``iterations``:
    the conjugate-gradient cap if not ``opt.cg_iterations``."""
    n = a.size
    repeat = residual.size // n
    at = np.tile(a, repeat)
    lam = opt.smoothness * float(np.median(weight[weight > 0]))
    prior = 1.0 / opt.gain_prior**2
    wr = weight * residual
    grad_s = A.back(at * wr) - (lam * (gram @ s) if priors else 0.0)
    grad_a = (predicted * wr).reshape(repeat, n).sum(axis=0) - (prior * (a - 1.0) if priors else 0.0)
    h_aa = gain_information(weight, predicted, n) + prior
    coupling = weight * at * predicted  # rows of H_sa = A^T diag(w a P), per reading
    data_ss = weight * at**2

    def schur(v):
        u = A.forward(v)
        back = (coupling * u).reshape(repeat, n).sum(axis=0) / h_aa
        return A.back(data_ss * u - coupling * np.tile(back, repeat)) + lam * (gram @ v)

    rhs = grad_s - A.back(coupling * np.tile(grad_a / h_aa, repeat))
    diagonal = A.back_squared(data_ss) + lam * gram.diagonal()
    ds, its = _pcg(schur, rhs, np.maximum(diagonal, 1e-12 * max(diagonal.max(), 1e-300)),
                   opt.cg_iterations if iterations is None else iterations, opt.cg_rtol)
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
