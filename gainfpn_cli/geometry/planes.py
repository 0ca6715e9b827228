"""The planes of a burst's frames and the grids solved on them.

A monochrome frame is one plane, an RGB EXR three, a CFA mosaic four (its 2x2 positions,
whose motion is estimated once on a grey proxy of 2x2 cells and mapped exactly to each
plane). ``S`` matrices map a plane's pixel coordinates to frame pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .cfa import OFFSETS, green_lattice, grey_proxy, plane_to_mosaic


@dataclass(frozen=True)
class Grid:
    """Photosites solved together: ``gather`` takes them out of an ``(..., H, W, C)``
    array as ``(..., h, w)`` grids, ``scatter(dst, grids)`` puts values back, and ``S``
    maps grid pixels to frame pixels. ``positions`` names the planes it covers, ``shape`` is
    ``(h, w)``."""

    name: str
    gather: Callable
    scatter: Callable
    S: np.ndarray
    positions: tuple[str, ...]
    shape: tuple[int, int]


def plane_views(cfa: str | None, channels: tuple[str, ...]):
    """(name, pick, S) per plane the gauge and the FPN model work on: the 2x2 positions of a
    CFA mosaic, or the channels; ``pick`` views the plane in an ``(..., H, W, C)`` array,
    ``S`` maps plane pixels to frame pixels."""
    if cfa:
        for (dy, dx), colour in zip(OFFSETS, cfa):
            yield f"{colour}@{dy}{dx}", (lambda a, dy=dy, dx=dx: a[..., dy::2, dx::2, 0]), plane_to_mosaic((dy, dx))
    else:
        for c, name in enumerate(channels):
            yield name, (lambda a, c=c: a[..., c]), np.eye(3)


def solve_grids(cfa: str | None, channels: tuple[str, ...], shape: tuple[int, int], *, greens_together: bool):
    """The grids a solver runs on: each plane, except that with ``greens_together`` the two
    greens of a CFA are taken together on their rotated lattice (:class:`cfa.GreenLattice`)."""
    lattice = green_lattice(cfa, shape) if cfa and greens_together else None
    if lattice is not None:
        greens = tuple(f"G@{dy}{dx}" for (dy, dx), colour in zip(OFFSETS, cfa) if colour == "G")

        def scatter(dst, grids):
            lattice.scatter(dst[..., 0], grids)

        yield Grid("G", lambda a: lattice.gather(a[..., 0]), scatter, lattice.S, greens, lattice.shape)
    nothing = np.broadcast_to(np.float32(0), tuple(shape) + (max(len(channels), 1),))  # a plane's shape, no copy
    for name, pick, S in plane_views(cfa, channels):
        if lattice is not None and name.startswith("G@"):
            continue

        def scatter(dst, grids, pick=pick):
            pick(dst)[...] = grids

        yield Grid(name, pick, scatter, S, (name,), pick(nothing).shape)


def motion_frames(frames: np.ndarray, cfa: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Grey images motion is estimated on, and S mapping their pixels to frame pixels."""
    if cfa:
        return np.stack([grey_proxy(f[..., 0]) for f in frames]), plane_to_mosaic((0.5, 0.5))
    if frames.shape[3] == 1:
        return frames[..., 0], np.eye(3)  # a view: no copy of a monochrome stack
    return frames.mean(axis=3), np.eye(3)


def frame_homography(H: np.ndarray, S: np.ndarray) -> list:
    """``H_t_ref`` of the motion images in frame pixels (mosaic photosites for RAW), as nested lists."""
    H = np.asarray(S) @ H @ np.linalg.inv(S)
    return (H / H[2, 2]).tolist()


def reference_cells(excluded: np.ndarray | None, shape: tuple[int, int], cfa: str | None) -> np.ndarray | None:
    """The reference's pixels masked as moving, on the motion images' ``shape`` grid (a CFA's 2x2 cells)."""
    if excluded is None:
        return None
    return excluded[0, ::2, ::2][: shape[0], : shape[1]] if cfa else excluded[0]
