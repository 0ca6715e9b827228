"""Resampling one frame onto another's pixel grid: ``dst(q) = src(M q)``.

``M`` is a 3x3 homography, or a float32 ``(h, w, 2)`` map holding ``M q``
for every ``q`` (a field motion model, :mod:`geometry.warps`). OpenCV's
``warpPerspective`` with ``WARP_INVERSE_MAP`` does the first without
building coordinate maps, ``remap`` the second. Both quantise sub-pixel
positions to 1/32 px (RMS position error 0.009 px), well below the 0.05 px
the motion estimate is allowed.
"""

from __future__ import annotations

import numpy as np

#: kernel name -> (OpenCV flag name, support radius in px)
KERNELS = {
    "bilinear": ("INTER_LINEAR", 1),
    "cubic": ("INTER_CUBIC", 2),
    "lanczos4": ("INTER_LANCZOS4", 4),
}


def _flag(kernel: str) -> int:
    import cv2

    try:
        return getattr(cv2, KERNELS[kernel][0])
    except KeyError:
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}") from None


def _resample(image: np.ndarray, M: np.ndarray, shape: tuple[int, int], flag: int, border: int) -> np.ndarray:
    import cv2

    h, w = shape
    if M.shape == (3, 3):
        return cv2.warpPerspective(image, np.asarray(M, np.float64), (w, h), flags=flag | cv2.WARP_INVERSE_MAP,
                                   borderMode=border, borderValue=0)
    if M.shape != (h, w, 2):
        raise ValueError(f"M must be 3x3 or a map of shape {(h, w, 2)}, got {M.shape}")
    return cv2.remap(image, np.asarray(M, np.float32), None, flag, borderMode=border, borderValue=0)


def sample(image: np.ndarray, M: np.ndarray, shape: tuple[int, int], *, kernel: str = "lanczos4") -> np.ndarray:
    """``out[q] = image(M q)`` for every pixel ``q`` of a ``shape`` grid (float32)."""
    import cv2

    return _resample(np.asarray(image, np.float32), M, shape, _flag(kernel), cv2.BORDER_REFLECT)


def bounded(M: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``M`` with a map's positions far outside a ``shape`` source brought to just outside it.

    OpenCV's reflecting border walks back into the frame one reflection at a
    time: a map holding :data:`geometry.warps.NOWHERE` for 5 % of its pixels
    remaps 7x slower (120x160, Lanczos-4: 2.8 ms against 0.4 ms). Samples
    there are invalid either way (:func:`valid_samples`). A 3x3 ``M`` is
    returned as it is.
    """
    if M.shape == (3, 3):
        return M
    margin = 2 * max(radius for _, radius in KERNELS.values())
    h, w = shape
    out = np.array(M, np.float32)
    np.clip(out[..., 0], -margin, w - 1 + margin, out=out[..., 0])
    np.clip(out[..., 1], -margin, h - 1 + margin, out=out[..., 1])
    return out


def positions(M: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``M q`` for every pixel ``q`` of a ``shape`` grid: float64 ``(h, w, 2)``."""
    if M.shape != (3, 3):
        return np.asarray(M, np.float64)
    from .warps import positions_from_homography

    return positions_from_homography(M, shape)


def valid_samples(good: np.ndarray, M: np.ndarray, shape: tuple[int, int], *, kernel: str = "lanczos4") -> np.ndarray:
    """Where :func:`sample` reads only good source pixels, all inside the source.

    ``good`` marks usable source pixels (not clipped, not dark). A sample is
    valid when every pixel of its kernel footprint is good: the bad set is
    grown by the kernel's radius (and the frame's border counts as bad).
    """
    import cv2

    radius = KERNELS[kernel][1]
    ok = np.asarray(good, np.uint8)
    ok = cv2.erode(ok, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                   borderValue=0)
    return _resample(ok, M, shape, cv2.INTER_NEAREST, cv2.BORDER_CONSTANT) > 0


def window_sum(image: np.ndarray, side: int) -> np.ndarray:
    """The sum over the ``side`` x ``side`` window around each pixel (edges mirrored), in the
    image's own dtype."""
    import cv2

    return cv2.boxFilter(image, -1, (side, side), normalize=False, borderType=cv2.BORDER_REFLECT)


def masked_window_mean(values: np.ndarray, mask: np.ndarray, side: int) -> np.ndarray:
    """The mean of float32 ``values`` over the ``mask`` pixels of the ``side`` x ``side`` window around
    each pixel; 0 where the window has none.

    Summed only over the mask's bounding box grown by half a window (a central region of a plane,
    not the plane): no window beyond it holds a mask pixel, and the mirrored border of the crop
    holds none either."""
    out = np.zeros(mask.shape, np.float32)
    rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return out
    half = side // 2
    box = (slice(max(rows[0] - half, 0), rows[-1] + half + 1), slice(max(columns[0] - half, 0), columns[-1] + half + 1))
    inside = mask[box]
    count = window_sum(inside.astype(np.float32), side)
    total = window_sum(np.where(inside, np.asarray(values, np.float32)[box], np.float32(0)), side)
    np.divide(total, count, out=out[box], where=count > 0)
    return out


def low_pass(image: np.ndarray, sigma: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Gaussian low-pass; with ``mask``, normalised so masked-out pixels do not count."""
    import cv2

    img = np.asarray(image, np.float32)
    blur = lambda a: cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    if mask is None:
        return blur(img).astype(np.float64)
    m = np.asarray(mask, np.float32)
    weight = blur(m).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = blur(img * m).astype(np.float64) / weight
    return np.where(weight > 1e-6, out, 1.0)
