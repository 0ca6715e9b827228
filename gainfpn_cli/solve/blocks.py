"""Image-level driver of the paper's block solver (``solver.method: paper``).

Frame 0 is tiled into non-overlapping ``block_size`` squares (edge blocks are
smaller). For each block, every trajectory ``p -> positions[t, p]`` gives one
residual row of paper eq. 5 with bilinear weights (Fig. 3); rows that leave
the frame or touch a saturated or non-positive sample are dropped. Each
block's constrained system is solved by :func:`solve.kkt._solve_gauged`, and the
``B`` part of its ``k`` is kept. Strips of block rows are independent tasks
for :func:`parallel.map_ordered`: every block is computed the same way
whatever the strip or worker, so results are bit-identical for any worker
count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import EstimationError
from ..geometry.warps import STILL_PX
from ..parallel import map_ordered
from .kkt import DENSE_MAX, OK, REGULARISED, UNESTIMATED, SolveOptions, _solve_gauged
from .result import GainResult, PaperStats, regauge


@dataclass(frozen=True)
class _Strip:
    """One task: a strip of block rows and the part of each frame it reaches."""

    y0: int
    frame0: np.ndarray  # (h, W) rows y0..y0+h of the reference
    positions: np.ndarray  # (F, h, W, 2) x, y in full-frame coordinates
    window_y0: int
    window: np.ndarray  # (F, hw, W) rows window_y0.. of frames 1..F
    shape: tuple[int, int]
    block_size: int
    options: SolveOptions
    saturation: float


def solve_paper(
    frames: np.ndarray,
    positions: np.ndarray,
    *,
    block_size: int = 5,
    options: SolveOptions = SolveOptions(),
    saturation: float | None = None,
    workers: int = 2,
    progress=None,
    executor=None,
) -> GainResult:
    """Estimate ``k`` block by block as published (paper eq. 5-6, bilinear).

    Parameters
    ----------
    frames : ndarray, shape (F+1, H, W)
        The reference frame first, then the others; DN, offset removed.
    positions : ndarray, shape (F, H, W, 2)
        Where each reference pixel is seen in frames 1..F, ``(x, y)`` px;
        NaN where unknown.
    saturation : float, optional
        Samples at or above this level are clipped and excluded.
    progress : callable, optional
        Called with the number of strips finished; ``progress.total`` is not
        needed (see :func:`n_tasks`).
    workers, executor
        Local processes that solve the strips, or a :class:`parallel.DaskExecutor` to solve
        them on instead.
    """
    frames = np.asarray(frames, dtype=np.float32)
    positions = np.asarray(positions, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must have shape (F+1, H, W) with F >= 1, got {frames.shape}")
    n_frames, h, w = frames.shape
    if positions.shape != (n_frames - 1, h, w, 2):
        raise ValueError(f"positions must have shape {(n_frames - 1, h, w, 2)}, got {positions.shape}")
    if block_size < 1:
        raise ValueError(f"block_size must be a positive integer, got {block_size}")
    moving = _moving_frames(positions)
    if not moving.any():
        raise EstimationError(
            f"no motion: every frame is within {STILL_PX} px RMS of the reference, "
            "so the gain cannot be estimated (pan or shake the camera during the burst)"
        )
    others, positions = frames[1:][moving], positions[moving]
    sat = np.inf if saturation is None else float(saturation)
    tasks = _strips(frames[0], others, positions, block_size, options, sat, workers)
    results = map_ordered(_solve_strip, tasks, workers=workers, progress=progress, executor=executor)
    k = np.concatenate([r[0] for r in results], axis=0)
    status = np.concatenate([r[1] for r in results], axis=0)
    rows = sum(r[2] for r in results)
    estimated = status != UNESTIMATED
    if estimated.any():
        regauge(k, estimated)
    k[~estimated] = 1.0
    confidence = np.select([status == OK, status == REGULARISED], [1.0, 0.5], 0.0)
    block_status = status[::block_size, ::block_size]
    stats = PaperStats(
        blocks=int(block_status.size),
        regularised=int((block_status == REGULARISED).sum()),
        unestimated_blocks=int((block_status == UNESTIMATED).sum()),
        unestimated_pixels=int((~estimated).sum()),
        static_frames=int((~moving).sum()),
        rows=int(rows),
    )
    return GainResult(k.astype(np.float32), confidence.astype(np.float32), stats)


def n_tasks(shape: tuple[int, int], block_size: int, workers: int) -> int:
    """How many strips :func:`solve_paper` makes (for a progress bar's total)."""
    block_rows = -(-shape[0] // block_size)
    return min(block_rows, max(4 * workers, block_rows // max(1, 64 // block_size)))


def _moving_frames(positions: np.ndarray) -> np.ndarray:
    h, w = positions.shape[1:3]
    ys, xs = np.mgrid[0:h, 0:w]
    d2 = (positions[..., 0] - xs) ** 2 + (positions[..., 1] - ys) ** 2
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.nanmean(d2.reshape(len(positions), -1), axis=1))
    return np.nan_to_num(rms, nan=0.0) >= STILL_PX


def _strips(frame0, others, positions, block_size, options, saturation, workers) -> list[_Strip]:
    h, w = frame0.shape
    block_rows = -(-h // block_size)
    per_strip = -(-block_rows // n_tasks((h, w), block_size, workers))
    tasks = []
    for y0 in range(0, h, per_strip * block_size):
        y1 = min(h, y0 + per_strip * block_size)
        pos = positions[:, y0:y1]
        ys = pos[..., 1][np.isfinite(pos[..., 1])]
        lo = int(np.clip(np.floor(ys.min()), 0, h - 1)) if ys.size else 0
        hi = int(np.clip(np.floor(ys.max()) + 1, 0, h - 1)) if ys.size else 0
        tasks.append(_Strip(y0, frame0[y0:y1], pos, lo, others[:, lo : hi + 1], (h, w), block_size, options,
                            saturation))
    return tasks


def _solve_strip(task: _Strip) -> tuple[np.ndarray, np.ndarray, int]:
    """k, status per pixel of the strip, and the number of residual rows used."""
    bs = task.block_size
    hs, w = task.frame0.shape
    k = np.ones((hs, w))
    status = np.full((hs, w), UNESTIMATED, np.int8)
    rows = 0
    for by in range(0, hs, bs):
        for bx in range(0, w, bs):
            sl = (slice(by, min(by + bs, hs)), slice(bx, min(bx + bs, w)))
            kb, sb, nr = _solve_one_block(task, sl)
            k[sl], status[sl], rows = kb, sb, rows + nr
    return k, status, rows


def _solve_one_block(task: _Strip, sl: tuple[slice, slice]) -> tuple[np.ndarray, int, int]:
    h, w = task.shape
    ry, rx = np.mgrid[sl]
    block_shape = ry.shape
    gy = (ry + task.y0).ravel()
    gx = rx.ravel()
    n_b = gy.size
    i0 = task.frame0[sl].ravel().astype(np.float64)
    pos = task.positions[:, sl[0], sl[1]].reshape(len(task.positions), n_b, 2)
    x, y = pos[..., 0], pos[..., 1]
    with np.errstate(invalid="ignore"):
        valid = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    valid &= ((i0 > 0) & (i0 < task.saturation))[None, :]
    x = np.where(valid, x, 0.0)
    y = np.where(valid, y, 0.0)
    x0 = np.clip(np.floor(x), 0, max(w - 2, 0)).astype(np.int64)
    y0 = np.clip(np.floor(y), 0, max(h - 2, 0)).astype(np.int64)
    fx, fy = x - x0, y - y0
    # the four bilinear taps (Fig. 3): offsets and weights, shape (4, F, n_B)
    tap_dy = np.array([0, 0, 1, 1])[:, None, None]
    tap_dx = np.array([0, 1, 0, 1])[:, None, None]
    weight = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx])
    present = weight > 0
    ty = np.where(present, y0[None] + tap_dy, y0[None])
    tx = np.where(present, x0[None] + tap_dx, x0[None])
    frame_index = np.arange(len(task.window))[None, :, None]
    values = task.window[frame_index, np.clip(ty - task.window_y0, 0, task.window.shape[1] - 1), tx]
    usable = ~present | ((values > 0) & (values < task.saturation))
    valid &= usable.all(axis=0)
    n_rows = int(valid.sum())
    if n_rows == 0:
        return np.ones(block_shape), UNESTIMATED, 0
    i_t = (weight * values).sum(axis=0)  # i~(p + d, t)
    f_idx, m_idx = np.nonzero(valid)
    row_of = np.cumsum(valid.ravel()).reshape(valid.shape) - 1
    b_global = gy * w + gx
    tap_global = (ty * w + tx)[:, f_idx, m_idx]  # (4, rows)
    tap_weight = np.where(present, weight, 0.0)[:, f_idx, m_idx]
    outside = np.setdiff1d(np.unique(tap_global[tap_weight > 0]), b_global)
    unknowns = np.concatenate([b_global, outside])
    order = np.argsort(unknowns, kind="stable")
    local = lambda g: order[np.searchsorted(unknowns, g, sorter=order)]  # noqa: E731
    r = row_of[f_idx, m_idx]
    coeff = -i_t[f_idx, m_idx][None, :] * tap_weight
    A = sp.coo_matrix(
        (np.concatenate([i0[m_idx], coeff.ravel()]),
         (np.concatenate([r, np.tile(r, 4)]), np.concatenate([local(b_global[m_idx]), local(tap_global).ravel()]))),
        shape=(n_rows, unknowns.size),
    ).tocsr()
    Q = A.T @ A
    touched = np.asarray(abs(A).sum(axis=0)).ravel() > 0
    keep = np.flatnonzero(touched)
    Q = Q[keep][:, keep]
    n_keep_b = int(touched[:n_b].sum())
    if n_keep_b == 0:
        return np.ones(block_shape), UNESTIMATED, n_rows
    Q = Q.toarray() if keep.size <= DENSE_MAX else Q.tocsc()
    k_r, state, _ = _solve_gauged(Q, lam=task.options.lam, max_condition=task.options.max_condition,
                                  check=slice(0, n_keep_b), k_range=task.options.k_range)
    k_b = np.ones(n_b)
    st = np.full(n_b, UNESTIMATED, np.int8)
    if state != UNESTIMATED:
        k_b[touched[:n_b]] = k_r[:n_keep_b]
        st[touched[:n_b]] = state
    return k_b.reshape(block_shape), st.reshape(block_shape), n_rows
