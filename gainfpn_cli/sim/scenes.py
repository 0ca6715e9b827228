"""Scenes to render bursts from: built-in textures (procedural, dead leaves) and photographs
read from files."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files.read import check_finite, read_oiio

#: Built-in scenes, by name. ``dead-leaves``'s smallest leaf (3 sensor pixels) makes the paper's
#: published form give about its published ratio (docs/method.md, Measured choices);
#: ``procedural`` is smoother (multi-scale noise and shapes of >= 1.5 px).
SCENES = ("procedural", "dead-leaves")


def procedural_scene(shape: tuple[int, int], rng: np.random.Generator, *, colour: bool = False) -> np.ndarray:
    """A natural-looking texture in [0.05, 0.95]: multi-scale noise plus shapes.

    Returns float32 ``(h, w)``, or ``(h, w, 3)`` with ``colour``.
    """
    import cv2

    h, w = shape
    grey = np.zeros(shape, np.float32)
    cell = 3
    while cell < max(h, w):
        grid = rng.standard_normal((h // cell + 4, w // cell + 4)).astype(np.float32)
        big = cv2.resize(grid, ((grid.shape[1]) * cell, (grid.shape[0]) * cell), interpolation=cv2.INTER_CUBIC)
        grey += cell**0.5 * big[cell : cell + h, cell : cell + w]
        cell *= 2
    grey = (grey - grey.mean()) / (grey.std() + 1e-12)
    n_shapes = max(8, h * w // 6000)
    for _ in range(n_shapes):
        level = float(rng.normal(0.0, 1.5))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        size = int(rng.integers(3, max(4, min(h, w) // 6)))
        if rng.random() < 0.5:
            cv2.circle(grey, (x, y), size, level, -1, lineType=cv2.LINE_AA)
        else:
            pts = np.array([[x, y], [x + size, y + int(rng.integers(-size, size + 1))], [x + int(rng.integers(-size, size + 1)), y + size]], np.int32)
            cv2.fillPoly(grey, [pts], level, lineType=cv2.LINE_AA)
    lo, hi = np.percentile(grey, [1, 99])
    grey = np.clip(0.05 + 0.9 * (grey - lo) / (hi - lo + 1e-12), 0.05, 0.95).astype(np.float32)
    if not colour:
        return grey
    tint_grid = rng.uniform(0.55, 1.0, size=(4, 4, 3)).astype(np.float32)
    tint = cv2.resize(tint_grid, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(grey[:, :, None] * tint, 0.02, 0.95).astype(np.float32)


def dead_leaves(shape: tuple[int, int], rng: np.random.Generator, *, r_min: float, r_max: float | None = None,
                colour: bool = False, coverage: float = 6.0) -> np.ndarray:
    """The dead-leaves texture of camera texture tests (ISO 19567-2, IEEE 1858).

    Opaque disks of uniform random value (or colour), radii distributed as
    ``r**-3`` on ``[r_min, r_max]``, drawn back to front ``coverage`` times
    over (so less than ``exp(-coverage)`` of the background shows). Its
    statistics are those of natural images: scale invariance, sharp
    occluding edges, a ``1/f**2`` power spectrum.

    Returns float32 ``(h, w)`` in [0.05, 0.95], or ``(h, w, 3)`` with ``colour``.
    Radii are in raster pixels; ``r_max`` defaults to a quarter of the longer side.
    """
    import cv2

    h, w = shape
    r_max = float(r_max or max(h, w) / 4)
    if not 0 < r_min < r_max:
        raise ValueError(f"need 0 < r_min < r_max, got {r_min}, {r_max}")
    span = 1.0 - (r_min / r_max) ** 2
    mean_area = np.pi * 2.0 * r_min**2 * np.log(r_max / r_min) / span
    n = int(np.ceil(coverage * (h + 2 * r_max) * (w + 2 * r_max) / mean_area))
    radius = r_min / np.sqrt(1.0 - rng.random(n) * span)  # inverse CDF of r**-3
    x = rng.uniform(-r_max, w + r_max, n)
    y = rng.uniform(-r_max, h + r_max, n)
    value = rng.uniform(0.05, 0.95, (n, 3 if colour else 1))
    out = np.full(shape + ((3,) if colour else ()), 0.5, np.float32)
    fixed = 16  # cv2 sub-pixel coordinates: 4 fractional bits
    for xi, yi, ri, vi in zip((x * fixed).astype(int), (y * fixed).astype(int), (radius * fixed).astype(int), value):
        cv2.circle(out, (int(xi), int(yi)), int(ri), vi.tolist(), -1, lineType=cv2.LINE_AA, shift=4)
    return out


def fit_scene(image: np.ndarray, shape: tuple[int, int], *, colour: bool) -> np.ndarray:
    """Resize (keeping aspect) and centre-crop a scene image to cover ``shape``."""
    import cv2

    if image.ndim == 3 and not colour:
        image = image[:, :, :3].mean(axis=2)
    elif image.ndim == 2 and colour:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.ndim == 3:
        image = image[:, :, :3] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
    factor = max(shape[0] / image.shape[0], shape[1] / image.shape[1])
    size = (max(shape[1], int(np.ceil(image.shape[1] * factor))), max(shape[0], int(np.ceil(image.shape[0] * factor))))
    resized = cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_CUBIC)
    y0, x0 = (resized.shape[0] - shape[0]) // 2, (resized.shape[1] - shape[1]) // 2
    return np.clip(resized[y0 : y0 + shape[0], x0 : x0 + shape[1]], 0.0, 1.0).astype(np.float32)


def read_scene(path: str | os.PathLike) -> np.ndarray:
    """Any image OpenImageIO reads, as a linear float32 scene in [0, 1].

    Integer files (PNG, JPEG, TIFF) are taken as sRGB-like and linearised
    with a 2.2 power; float files are used as they are, clipped to [0, 1].
    Returns ``(h, w)`` or ``(h, w, C)``.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    image, spec = read_oiio(path, what="image", require_exr=False)
    is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    check_finite(image, path)
    image = np.clip(image, 0.0, 1.0)
    if not is_float:
        image = image**2.2
    return image[:, :, 0] if image.shape[2] == 1 else image
