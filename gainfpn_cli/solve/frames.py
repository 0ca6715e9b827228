"""Each frame's registration and exposure refined against the scene solver's model
(docs/method.md section 8b): the joint motion refinement that pairwise comparisons cannot
converge. Pure array functions; :mod:`solve.scene` calls them between its Gauss-Newton steps."""

from __future__ import annotations

import numpy as np

from .sampling import compiled


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
    would discount the edges that show a misregistration most). A frame's change counts only where
    its step is significant against the noise (chi-square of its 13 parameters above
    :data:`REFINE_CHI2`): warps the burst follows are left as they are. The steps are taken about
    their mean over the frames. Returns ``(moves (frames, pixels, 2) grid px, exposure factors
    (frames,), material (frames,))``: the moves and factors of every frame whose step is
    significant (zero moves and factor 1 elsewhere), and which of them are also material (RMS move
    above ``refine_px`` or exposure change above ``refine_exposure``)."""
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
        H, g = np.zeros((2 * m + 1, 2 * m + 1)), np.zeros(2 * m + 1)
        _normal_equations(a * slope_x[at_t], a * slope_y[at_t], a * predicted[at_t], weight[t], residual[at_t], u, v,
                          H, g)
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
    material = np.zeros(n_frames, bool)
    gram = basis.T @ basis / n  # a field's mean square from its coefficients
    for t in range(n_frames):
        if chi2[t] > REFINE_CHI2 and np.all(np.isfinite(steps[t])):
            moves[t] = np.stack([basis @ steps[t, :m], basis @ steps[t, m:2 * m]], axis=1)
            gains[t] = 1.0 + steps[t, 2 * m]
            rms = np.sqrt(max(steps[t, :m] @ gram @ steps[t, :m] + steps[t, m:2 * m] @ gram @ steps[t, m:2 * m], 0.0))
            material[t] = rms > refine_px or abs(steps[t, 2 * m]) > refine_exposure
    return moves, gains, material


@compiled
def _normal_equations(ax, ay, ap, weight, residual, u, v, H, g):
    """Add one frame's weighted normal equations ``J^T W J`` and ``J^T W r`` to ``H`` and ``g``: per
    reading the Jacobian row is the quadratic basis ``1, u, v, u^2, uv, v^2`` times the slopes
    ``ax``, then times ``ay``, then the level ``ap`` (the exposure)."""
    m = 6
    j = np.empty(2 * m + 1)
    for i in range(weight.size):
        w = weight[i]
        if w == 0.0:
            continue
        j[0], j[1], j[2] = 1.0, u[i], v[i]
        j[3], j[4], j[5] = u[i] * u[i], u[i] * v[i], v[i] * v[i]
        for c in range(m):
            j[m + c] = ay[i] * j[c]
            j[c] = ax[i] * j[c]
        j[2 * m] = ap[i]
        wr = w * residual[i]
        for c in range(2 * m + 1):
            wc = w * j[c]
            g[c] += j[c] * wr
            for d in range(c, 2 * m + 1):
                H[c, d] += wc * j[d]
    for c in range(2 * m + 1):
        for d in range(c):
            H[c, d] = H[d, c]


def rms_move(moves: np.ndarray):
    """The RMS length of ``moves`` ``(..., pixels, 2)`` (grid px): per frame for a stack of them."""
    return np.sqrt(np.mean(np.sum(moves**2, axis=-1), axis=-1))


#: Chi-square of a frame's 13 refinement parameters above which the step is more than noise
#: (its 0.999 quantile).
REFINE_CHI2 = 34.53
