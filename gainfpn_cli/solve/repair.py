"""Defective photosites filled from their healthy neighbours in their plane (a CFA colour's own
lattice): in the frames while they are solved and in the corrected frames (docs/method.md section 12b)."""

from __future__ import annotations

import numpy as np

from ..geometry.resample import window_sum
from .defects import SAFE_PEAK
from .tiling import power_of_two_scale


#: Neighbourhoods a defective photosite is filled from, growing until one holds a healthy
#: photosite: 3x3, 5x5, ... of its plane (a CFA colour's own lattice).
REPAIR_ROUNDS = 8


def fill(plane: np.ndarray, defective: np.ndarray) -> np.ndarray:
    """``plane`` ``(H, W)`` with every ``defective`` photosite replaced by the mean of its healthy
    neighbours in the plane (the nearest ring that has any); float32. Photosites with no healthy
    neighbour within :data:`REPAIR_ROUNDS` rings keep their value."""
    image = np.array(plane, np.float32)
    if not defective.any():
        return image
    image[defective] = 0  # a stuck or hot reading may be anything, inf included
    known = (~defective).astype(np.float32)
    # summed in units of a power of two near the level where the sums could overflow (exact)
    unit = power_of_two_scale(image) if float(image.max(initial=0.0)) > SAFE_PEAK[1] else 1.0
    weight = known / np.float32(unit)
    todo = defective.copy()
    for radius in range(1, REPAIR_ROUNDS + 1):
        total = window_sum(image * weight, 2 * radius + 1)
        count = window_sum(known, 2 * radius + 1)
        filled = todo & (count > 0.5)
        image[filled] = total[filled] / count[filled] * np.float32(unit)
        todo &= ~filled
        if not todo.any():
            break
    return image
