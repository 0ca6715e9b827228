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


#: The quadratic basis's exponents ``(i, j)`` of ``u^i v^j``, the 15 monomials of degree up to 4 its
#: products make (in :func:`_moments`' order), and where each product of two basis functions falls.
_BASIS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
_MONOMIALS = tuple((i - j, j) for i in range(5) for j in range(i + 1))
_PRODUCT = np.array([[_MONOMIALS.index((b[0] + c[0], b[1] + c[1])) for c in _BASIS] for b in _BASIS])


def _normal_equations(ax, ay, ap, weight, residual, u, v, H, g):
    """Add one frame's weighted normal equations ``J^T W J`` and ``J^T W r`` to ``H`` and ``g``: per
    reading the Jacobian row is the quadratic basis ``1, u, v, u^2, uv, v^2`` times the slopes
    ``ax``, then times ``ay``, then the level ``ap`` (the exposure).

    A block of ``J^T W J`` between two slopes sums products of two basis functions, monomials of
    degree up to 4: the readings' weighted moments are summed (:func:`_moments`), 81 sums instead of
    the 104 of each row's products, and over chunks of readings, which vectorises (2.3 against 4.7
    ms for 160 000 readings, one run)."""
    moments, rows = np.zeros((3, 15)), np.zeros((6, 6))
    _moments(ax, ay, ap, weight, residual, u, v, moments, rows)
    xx, xy, yy = (m[_PRODUCT] for m in moments)
    H += np.block([[xx, xy, rows[0][:, None]], [xy, yy, rows[1][:, None]],
                   [rows[0][None, :], rows[1][None, :], rows[2][:1, None]]])
    g += np.concatenate([rows[3], rows[4], rows[5][:1]])


#: Readings per chunk of :func:`_moments` (their factors fit in the first-level cache).
_CHUNK = 64


@compiled
def _moments(ax, ay, ap, weight, residual, u, v, moments, rows):
    """The sums of :func:`_normal_equations` into ``moments`` (3, 15): ``w ax^2``, ``w ax ay`` and
    ``w ay^2`` times each monomial of :data:`_MONOMIALS`; and ``rows`` (6, 6): ``w ax ap``, ``w ay
    ap``, ``w ap^2``, ``w r ax``, ``w r ay`` and ``w r ap`` times each basis function (of the third
    and the last, only the first column is used)."""
    chunk = _CHUNK
    q = np.zeros((9, chunk))
    mono = np.zeros((15, chunk))
    for start in range(0, weight.size, chunk):
        m = min(chunk, weight.size - start)
        for j in range(m):
            i = start + j
            w, x, y = weight[i], u[i], v[i]
            if w == 0.0:  # a reading not used: its slopes need not be finite
                for a in range(9):
                    q[a, j] = 0.0
                continue
            xx, xy, yy = x * x, x * y, y * y
            mono[0, j], mono[1, j], mono[2, j], mono[3, j], mono[4, j], mono[5, j] = 1.0, x, y, xx, xy, yy
            mono[6, j], mono[7, j], mono[8, j], mono[9, j] = x * xx, y * xx, x * yy, y * yy
            mono[10, j], mono[11, j], mono[12, j], mono[13, j], mono[14, j] = xx * xx, xx * xy, xx * yy, xy * yy, \
                yy * yy
            wx, wy, wr = w * ax[i], w * ay[i], w * residual[i]
            q[0, j], q[1, j], q[2, j] = wx * ax[i], wx * ay[i], wy * ay[i]
            q[3, j], q[4, j], q[5, j] = wx * ap[i], wy * ap[i], w * ap[i] * ap[i]
            q[6, j], q[7, j], q[8, j] = wr * ax[i], wr * ay[i], wr * ap[i]
        for j in range(m, chunk):  # the last chunk's unused places weigh nothing
            for a in range(9):
                q[a, j] = 0.0
        for a in range(3):
            for k in range(15):
                total = 0.0
                for j in range(chunk):
                    total += q[a, j] * mono[k, j]
                moments[a, k] += total
        for a in range(6):
            for k in range(6):
                total = 0.0
                for j in range(chunk):
                    total += q[3 + a, j] * mono[k, j]
                rows[a, k] += total


def rms_move(moves: np.ndarray):
    """The RMS length of ``moves`` ``(..., pixels, 2)`` (grid px): per frame for a stack of them."""
    return np.sqrt(np.mean(np.sum(moves**2, axis=-1), axis=-1))


#: Chi-square of a frame's 13 refinement parameters above which the step is more than noise
#: (its 0.999 quantile).
REFINE_CHI2 = 34.53
