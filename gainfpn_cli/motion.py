"""Motion: where each reference pixel is seen in every other frame.

Conventions (METHOD.md section 6): arrays are ``(row, col)``; points are
``(x, y)``; ``H_t_ref`` maps reference pixel coordinates to frame ``t``;
``flow_xy[..., 0] = dx``, ``flow_xy[..., 1] = dy``.
"""

from __future__ import annotations

import numpy as np


def positions_from_homography(H: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Position in frame t of every reference pixel, for ``H = H_t_ref``.

    Returns
    -------
    ndarray of float64, shape (H, W, 2)
        ``[..., 0]`` = x, ``[..., 1]`` = y in frame t's pixel coordinates.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"H must be a finite 3x3 matrix, got shape {H.shape}")
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    den = H[2, 0] * xs + H[2, 1] * ys + H[2, 2]
    out = np.empty((h, w, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        out[..., 0] = (H[0, 0] * xs + H[0, 1] * ys + H[0, 2]) / den
        out[..., 1] = (H[1, 0] * xs + H[1, 1] * ys + H[1, 2]) / den
    out[~np.isfinite(out)] = np.nan  # points sent to infinity have no position
    return out


def positions_from_flow(flow_xy: np.ndarray) -> np.ndarray:
    """Position in the moving frame of every reference pixel: ``p + flow``."""
    flow_xy = np.asarray(flow_xy, dtype=np.float64)
    if flow_xy.ndim != 3 or flow_xy.shape[2] != 2:
        raise ValueError(f"flow_xy must have shape (H, W, 2), got {flow_xy.shape}")
    h, w = flow_xy.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([xs + flow_xy[..., 0], ys + flow_xy[..., 1]], axis=-1)
