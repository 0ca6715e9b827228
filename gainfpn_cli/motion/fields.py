"""Fitting the field models of :class:`geometry.warps.FieldWarp` to tracked points.

Frame t sees reference point p at ``q = H p + r(q)`` (see :mod:`geometry.warps`),
so a tracked pair ``(src, dst)`` gives ``r(dst) = dst - H src``: ``H`` and the field's coefficients are fitted
together (penalised Gauss-Newton, :func:`joint_fit`).

The points are accurate to a few hundredths of a pixel; dense optical flow
is not (DIS flow of these frames errs by 0.1-1 px per pixel, measured), so
the field is fitted to the points and flow only checks it afterwards
(:func:`motion.masks.moving_masks`). Cells with few points are held smooth by a
P-spline penalty (squared second differences of the coefficients) whose
weight generalised cross-validation picks, so a real wobble is not damped
and an unconstrained corner does not swing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.warps import DEGREE, apply_homography, basis, field_at
from ..metrics import point_noise_variance

#: Cells (y, x) of each field model; x = 0: a field of the row alone.
#: ``rolling``: a rolling shutter's per-row displacement (12 cells follow a
#: vibration of up to about 3 periods over the frame); ``mesh``: a smooth
#: displacement over the whole frame.
FIELD_CELLS = {"rolling": (12, 0), "mesh": (4, 4)}
#: Points farther than this (px) from the starting homography do not enter
#: the fit (a fast moving object). The others are weighted by Cauchy's
#: ``1 / (1 + (e / (CAUCHY sigma))^2)`` of their residual ``e`` in units of
#: the noise, refitted up to ROUNDS times: a hard inlier cut, tried first,
#: kept all of a slow object's points once the first fit had bent to them.
START_PX = 10.0
ROUNDS = 15
CAUCHY = 2.4
#: The points reported as kept (and counted by the noise estimate): within
#: ROBUST_SIGMAS x the residual noise, or KEEP_FLOOR_PX (the global fit's
#: inlier threshold).
ROBUST_SIGMAS = 3.0
KEEP_FLOOR_PX = 0.3
#: Penalty weights tried by generalised cross-validation, relative to
#: ``trace(B^T B) / trace(P)``.
LAMBDAS = 10.0 ** np.arange(-6.0, 3.0)
#: Ridge on the coefficients, relative to the same scale: it settles what the homography explains
#: as well (docs/method.md, Measured choices: 1e-7 let the two drift apart by tens of pixels).
RIDGE = 1e-4
#: Gauss-Newton steps per fit (each reweighting round re-linearises anyway;
#: 5 gave the same trajectories, measured on 27 bursts).
GAUSS_NEWTON = 2


@dataclass(frozen=True)
class FieldFit:
    """A field model fitted to one frame's points.

    Attributes
    ----------
    H : ndarray (3, 3)
    coefficients : ndarray (2, ny, nx)
    keep : ndarray of bool
        The points the final fit used.
    dof : float
        Effective parameters: the trace of the joint fit's hat matrix (the
        homography's 8 and the field's penalised coefficients of both axes).
    """

    H: np.ndarray
    coefficients: np.ndarray
    keep: np.ndarray
    dof: float


def design(points: np.ndarray, shape: tuple[int, int], cells: tuple[int, int]) -> np.ndarray:
    """``(n, ny nx)`` basis values of the field at ``(x, y)`` points."""
    by = basis(points[:, 1], shape[0], cells[0])
    if cells[1] == 0:
        return by
    bx = basis(points[:, 0], shape[1], cells[1])
    return np.einsum("ni,nj->nij", by, bx).reshape(len(points), -1)


def roughness(cells: tuple[int, int]) -> np.ndarray:
    """``D^T D`` of the second differences of the coefficient grid along each axis."""
    ny, nx = _grid_shape(cells)

    def second(n: int) -> np.ndarray:
        d = np.diff(np.eye(n), 2, axis=0)
        return d.T @ d

    if nx == 1:
        return second(ny)
    return np.kron(second(ny), np.eye(nx)) + np.kron(np.eye(ny), second(nx))


def _homography_jacobian(hn: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Hn pts`` and its derivative ``(n, 2, 8)`` in the 8 entries of ``Hn`` (``Hn[2, 2] = 1``)."""
    x, y = pts[:, 0], pts[:, 1]
    w = hn[6] * x + hn[7] * y + 1.0
    u = (hn[0] * x + hn[1] * y + hn[2]) / w
    v = (hn[3] * x + hn[4] * y + hn[5]) / w
    jac = np.zeros((len(pts), 2, 8))
    jac[:, 0, 0:3] = np.stack([x, y, np.ones_like(x)], axis=1) / w[:, None]
    jac[:, 1, 3:6] = jac[:, 0, 0:3]
    jac[:, 0, 6:8] = -(u / w)[:, None] * pts
    jac[:, 1, 6:8] = -(v / w)[:, None] * pts
    return np.stack([u, v], axis=1), jac


def joint_fit(src: np.ndarray, dst: np.ndarray, H: np.ndarray, a: np.ndarray, penalty: np.ndarray,
              shape: tuple[int, int], weights: np.ndarray | None = None, lambdas=LAMBDAS
              ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``H`` and field coefficients ``c`` ``(m, 2)`` minimising
    ``sum_i w_i |H src_i + a_i c - dst_i|^2 + lam c^T P c + eps |c|^2``.

    One penalised Gauss-Newton problem for both, so neither drifts along
    what the other explains as well (a constant or linear field is a change
    of ``H``: the faint ridge ``eps`` gives it to ``H``). ``H`` is fitted in
    coordinates scaled to about [-1, 1]; ``lam`` is chosen by generalised
    cross-validation among ``lambdas`` at each step. Returns
    ``(H, c, hat-matrix trace, lam)``.
    """
    n, m = a.shape
    half = max(shape) / 2.0
    T = np.array([[1 / half, 0, -shape[1] / 2 / half], [0, 1 / half, -shape[0] / 2 / half], [0, 0, 1.0]])
    Hn = T @ H @ np.linalg.inv(T)
    hn = (Hn / Hn[2, 2]).ravel()[:8]
    src_n = apply_homography(T, src)
    coef = np.zeros((m, 2))
    scale = np.trace(a.T @ a) / m  # mean data weight per coefficient
    rough = penalty * scale / max(np.trace(penalty) / m, 1e-12)
    field_jac = np.zeros((n, 2, 2 * m))  # unknowns: 8 of H, then the x part's m, then the y part's m
    field_jac[:, 0, :m] = a
    field_jac[:, 1, m:] = a
    root = np.sqrt(np.ones(n) if weights is None else weights)[:, None, None]
    field_jac *= root
    trace = 0.0
    for _ in range(GAUSS_NEWTON):
        moved, jac_h = _homography_jacobian(hn, src_n)
        jac = np.concatenate([root * half * jac_h, field_jac], axis=2).reshape(2 * n, 8 + 2 * m)
        resid = (root[:, :, 0] * (half * moved + [shape[1] / 2, shape[0] / 2] + a @ coef - dst)).reshape(-1)
        jtj, jtr = jac.T @ jac, jac.T @ resid
        best = None
        for lam in lambdas:
            block = lam * rough + RIDGE * scale * np.eye(m)
            reg = np.zeros_like(jtj)
            reg[8 : 8 + m, 8 : 8 + m] = reg[8 + m :, 8 + m :] = block
            system = jtj + reg
            step = np.linalg.solve(system, -(jtr + reg[:, 8:] @ coef.T.ravel()))
            tr = float(np.trace(np.linalg.solve(system, jtj)))
            rss = float(np.sum((resid + jac @ step) ** 2))
            gcv = 2 * n * rss / max(2 * n - tr, 1e-3) ** 2
            if best is None or gcv < best[0]:
                best = (gcv, step, tr, lam)
        _, step, trace, chosen = best
        hn = hn + step[:8]
        coef = coef + step[8:].reshape(2, m).T
        if np.max(np.abs(step[8:])) < 1e-5 and np.max(np.abs(half * step[:8])) < 1e-5:
            break
    H = np.linalg.inv(T) @ np.append(hn, 1.0).reshape(3, 3) @ T
    return H / H[2, 2], coef, trace, chosen


def fit_field(src: np.ndarray, dst: np.ndarray, H0: np.ndarray, shape: tuple[int, int], model: str) -> FieldFit:
    """Fit field model ``model`` (a key of FIELD_CELLS) to one frame's point pairs, from homography ``H0``."""

    cells = FIELD_CELLS[model]
    a_all = design(dst, shape, cells)
    penalty = roughness(cells)
    m = a_all.shape[1]
    near = np.linalg.norm(apply_homography(H0, src) - dst, axis=1) < START_PX
    if near.sum() < max(m, 8) + 1:  # too few points to fit: the starting homography, no field, nothing kept
        return FieldFit(H0, np.zeros((2,) + _grid_shape(cells)), np.zeros(len(src), bool), 8.0)
    H, weights, lambdas = H0, near.astype(np.float64), LAMBDAS
    for _ in range(ROUNDS):  # iteratively reweighted: Cauchy weights on the residuals
        # the penalty weight is chosen (GCV) in the first round and kept while the weights settle
        H, coef, trace, lam = joint_fit(src[near], dst[near], H, a_all[near], penalty, shape, weights[near], lambdas)
        lambdas = [lam]
        residual = np.linalg.norm(apply_homography(H, src) + a_all @ coef - dst, axis=1)
        sigma = np.sqrt(max(point_noise_variance(residual[weights > 0.5]), 1e-10))
        updated = near / (1.0 + (residual / (CAUCHY * sigma)) ** 2)
        if np.max(np.abs(updated - weights)) < 0.01:
            break
        weights = updated
    H, coef, trace, _ = joint_fit(src[near], dst[near], H, a_all[near], penalty, shape, weights[near])  # GCV again
    residual = np.linalg.norm(apply_homography(H, src) + a_all @ coef - dst, axis=1)
    keep = residual < max(ROBUST_SIGMAS * sigma * np.sqrt(2), KEEP_FLOOR_PX)
    return FieldFit(H, coef.T.reshape((2,) + _grid_shape(cells)), keep, trace)


def _grid_shape(cells: tuple[int, int]) -> tuple[int, int]:
    return cells[0] + DEGREE, (1 if cells[1] == 0 else cells[1] + DEGREE)


def residuals(fit: FieldFit, src: np.ndarray, dst: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Distances (px) between where the fit puts ``src`` and ``dst``, measured as ``|H src + r(dst) - dst|``."""
    return np.linalg.norm(apply_homography(fit.H, src) + field_at(fit.coefficients, dst, shape) - dst, axis=1)
