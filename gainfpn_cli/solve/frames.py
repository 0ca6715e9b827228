"""Each frame's registration and exposure refined against the scene solver's model
(docs/method.md section 8b): the joint motion refinement that pairwise comparisons cannot
converge. Pure array functions; :mod:`solve.scene` calls them between its Gauss-Newton steps."""

from __future__ import annotations

import numpy as np


def refine_frames(forward, s, predicted, a, y, valid, noise, shape, *, scale: int, refine_px: float,
                  refine_exposure: float):
    """One Gauss-Newton step of every frame's warp and exposure against a fitted scene and gains.

    ``forward`` samples a fine scene (``scale`` samples per grid px of a ``shape`` grid) at every
    frame's readings, as the frames are now registered; ``s`` is the scene, ``predicted`` its
    ``forward``, ``a`` the gains, ``y`` the readings (frame-major), ``valid`` the readings used and
    ``noise`` the ``(alpha, beta)`` of their variance ``alpha + beta * level``.

    Where frame ``t``'s pixels see the first frame moves by a quadratic field over the tile (6
    coefficients per axis) and its exposure by a factor, fitted to the residuals with the noise
    model's weights (plain squares: discounting the worst-fitting readings, as the scene step does,
    would discount the edges that show a misregistration most). A frame is changed only where the
    step is significant against the noise (chi-square of its 13 parameters above
    :data:`REFINE_CHI2`) and material (RMS move above ``refine_px`` or exposure change above
    ``refine_exposure``): warps the burst follows are left as they are. The steps are taken about
    their mean over the frames. Returns ``(moves (frames, pixels, 2) grid px, exposure factors
    (frames,))``."""
    n = a.size
    n_frames = y.size // n
    grid = s.reshape(scale * shape[0], scale * shape[1])
    gx = np.gradient(grid, axis=1).reshape(-1) * scale  # per grid px
    gy = np.gradient(grid, axis=0).reshape(-1) * scale
    slope_x, slope_y = forward(gx), forward(gy)
    residual = y - np.tile(a, n_frames) * predicted
    alpha, beta = noise
    weight = (valid / np.maximum(alpha + beta * np.abs(predicted), 1e-12)).reshape(n_frames, n)
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    u, v = (cols.reshape(-1) + 0.5) / shape[1] - 0.5, (rows.reshape(-1) + 0.5) / shape[0] - 0.5
    basis = np.stack([np.ones(n), u, v, u * u, u * v, v * v], axis=1)
    m = basis.shape[1]
    steps = np.zeros((n_frames, 2 * m + 1))
    chi2 = np.zeros(n_frames)
    for t in range(n_frames):
        at_t = slice(t * n, (t + 1) * n)
        J = np.concatenate([(a * slope_x[at_t])[:, None] * basis, (a * slope_y[at_t])[:, None] * basis,
                            (a * predicted[at_t])[:, None]], axis=1)
        H = J.T @ (weight[t][:, None] * J)
        g = J.T @ (weight[t] * residual[at_t])
        try:
            steps[t] = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            continue
        chi2[t] = steps[t] @ g
    # the gauge: the scene's own place and level are free, so the frames move about their mean
    # (pinning one frame instead leaves the others a common drift that the scene barely resists)
    steps -= steps.mean(axis=0)
    moves = np.zeros((n_frames, n, 2))
    gains = np.ones(n_frames)
    for t in range(n_frames):
        move = np.stack([basis @ steps[t, :m], basis @ steps[t, m:2 * m]], axis=1)
        material = (rms_move(move) > refine_px
                    or abs(steps[t, 2 * m]) > refine_exposure)
        if material and chi2[t] > REFINE_CHI2 and np.all(np.isfinite(steps[t])):
            moves[t], gains[t] = move, 1.0 + steps[t, 2 * m]
    return moves, gains


def rms_move(moves: np.ndarray):
    """The RMS length of ``moves`` ``(..., pixels, 2)`` (grid px): per frame for a stack of them."""
    return np.sqrt(np.mean(np.sum(moves**2, axis=-1), axis=-1))


#: Chi-square of a frame's 13 refinement parameters above which the step is more than noise
#: (its 0.999 quantile).
REFINE_CHI2 = 34.53
