"""The hold-out check: does k reduce the brightness-constancy residual on a frame it was not
fitted to?"""

from __future__ import annotations

import numpy as np

from ..geometry.resample import sample, valid_samples
from .accurate import power_of_two_scale


def holdout_ratio(frames, excluded, exposures, in_frame, k, *, grids, saturation: float | None) -> float:
    """Brightness-constancy residual of the held-out frame against the reference, with k over without
    (the held-out frame brought to the reference's exposure). ``frames`` hold the reference first
    and the held-out frame last; ``grids`` are :func:`geometry.planes.solve_grids`."""
    num = den = 0.0
    sat = np.inf if saturation is None else saturation
    scale = np.float32(power_of_two_scale(frames[0]))  # about 1: k times a frame stays far from float32's limits
    for grid in grids:
        ref, held, kp = grid.gather(frames[0]), grid.gather(frames[-1]), grid.gather(k)
        ref_ok, held_ok = (ref > 0) & (ref < sat), (held > 0) & (held < sat)
        if excluded is not None:
            ref_ok &= ~grid.gather(np.broadcast_to(excluded[0, ..., None], frames.shape[1:]))
            held_ok &= ~grid.gather(np.broadcast_to(excluded[-1, ..., None], frames.shape[1:]))
        ref, held = ref / scale, held / (scale * np.float32(exposures[-1]))
        shape = ref.shape
        M = in_frame.conjugate(grid.S).pair(0, len(frames) - 1, (0, 0) + shape)
        valid = valid_samples(held_ok, M, shape) & ref_ok
        with_k = kp * ref - sample(kp * held, M, shape)
        without = ref - sample(held, M, shape)
        num += float(np.sum(with_k[valid] ** 2))
        den += float(np.sum(without[valid] ** 2))
    return num / den if den > 0 else 1.0
