"""Photosites too dark to solve: those whose mean reading is less than ``solver.min_snr`` times its
noise. On readings that noisy against their level a least-squares gain is biased low (regression
dilution) and the bias moves the gauge of the photosites around (docs/limits.md, "The hold-out
check"). The noise is the one the defect search measures on each plane (:mod:`solve.noise`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .geometry.planes import plane_views
from .geometry.resample import window_sum
from .solve.result import confidence_from_sigma

#: Side (plane px) of the window whose mean level decides that photosites are too dark to solve: a
#: left-out photosite takes every comparison whose interpolation reaches it with it, so scattered
#: dark ones in a brighter neighbourhood are kept (measured on 96x128 6-frame paper dead leaves at
#: 15 %, seed 1: 0.56 % of photosites left out one by one turned the accurate map's check from
#: 0.797 +- 0.042 to 0.915 +- 0.102, rejected; 0.02 % by a 5 px window left it as it was).
DARK_WINDOW = 5
#: A plane with more than this share of its photosites too dark to solve is warned of.
DARK_WARNING = 0.1


#: Highest floor, as a share of the full scale: the noise the defect search measures is the readings'
#: scatter about the scene predicted from the other frames, and on a fine texture in a CFA plane that
#: prediction errs by far more than the noise (RGGB `grass` and `brick` at a 40 % mean level: 240-300 DN
#: at 900-2300 DN, floors at 34-60 % of full scale, every photosite "too dark"). No sensor a lab
#: calibrates reads an SNR under 5 at 5 % of its full scale (a 2000 e- well with 10 e- read noise
#: reaches 5 at 3.2 %; the simulator's sensors at 0.16 % (raw12) and 0.85 % (paper)).
MAX_FLOOR = 0.05


def floors(noise: dict, min_snr: float, full_scale: float | None = None) -> dict:
    """Each plane's level (DN) at or below which its photosites are too dark: where a reading is
    ``min_snr`` times its noise (``noise``: plane name -> :class:`solve.noise.NoiseModel`, or None: no
    floor), at most :data:`MAX_FLOOR` of ``full_scale`` (DN; None: unknown, no limit)."""
    ceiling = np.inf if full_scale is None else MAX_FLOOR * full_scale
    return {name: 0.0 if model is None else min(model.level_at_snr(min_snr), ceiling) for name, model in noise.items()}


def too_dark(burst, frames: np.ndarray, floors: dict | None) -> np.ndarray | None:
    """The photosites whose mean reading over ``frames`` ``(F, H, W, C)``, averaged over the
    :data:`DARK_WINDOW` window of their plane, is at or below their plane's floor (``floors``: plane
    name -> DN), ``(H, W, C)`` bool; None where none is (or no floor is set)."""
    import cv2

    if not floors or not any(floors.values()):
        return None
    level = frames.mean(axis=0, dtype=np.float64).astype(np.float32)  # (a float32 sum can overflow)
    dark = np.zeros(level.shape, bool)
    for name, pick, _ in plane_views(burst.cfa, burst.channels):
        around = cv2.blur(np.ascontiguousarray(pick(level)), (DARK_WINDOW, DARK_WINDOW), borderType=cv2.BORDER_REPLICATE)
        pick(dark)[...] = around <= floors.get(name, 0.0)
    return dark if dark.any() else None


def reported(burst, frames: np.ndarray, floors: dict | None, reports: dict, min_snr: float) -> tuple[dict, list[str]]:
    """``reports`` (plane name -> :class:`report.PlaneReport`) with each plane's floor and share of
    photosites too dark over ``frames``, and a warning for each plane with more than
    :data:`DARK_WARNING` of them."""
    if not floors:
        return reports, []
    dark = too_dark(burst, frames, floors)
    out, warned = dict(reports), []
    for name, pick, _ in plane_views(burst.cfa, burst.channels):
        if name not in out or name not in floors:
            continue
        share = 0.0 if dark is None else float(pick(dark).mean())
        out[name] = dataclasses.replace(out[name], floor_dn=floors[name], too_dark_percent=100 * share)
        if share > DARK_WARNING:
            warned.append(f"{100 * share:.0f} % of plane {name}'s photosites read on average less than {min_snr:g} "
                          f"times their noise ({floors[name]:.1f} DN or less): too dark to estimate, so k = 1 (no "
                          "correction) there; more light would help")
    return out, warned


def noise_bounded(burst, frames: np.ndarray, confidence: np.ndarray, noise: dict | None) -> None:
    """Raise ``confidence``'s sigma_k, in place, to at least the bound its photosite's readings set with
    the scene known (``sigma_k^2 >= v(L) / (n L^2)``: ``n`` readings of mean ``L``, ``v`` the plane's
    noise model, ``noise``: plane name -> :class:`solve.noise.NoiseModel`) where a photosite of its
    :data:`DARK_WINDOW` window read black in some frame (``frames``, ``(F, H, W, C)``, those fitted) or
    was left unestimated (confidence 0).

    Readings kept above black there are the noise's high draws, which the pairwise prediction follows,
    so their residuals read below the noise: 8-bit `astronaut` at a 7.5 % mean level (240x320, 5 frames)
    gave photosites reading 1-2 DN a sigma_k of 0.7-1.5 % for errors of 10-45 % (the lowest tenth of
    sigma_k 1.62x its prediction; 0.98-1.10 bounded). A window with photosites left out (beside those too
    dark to solve, the frame's border, defects) holds fewer residuals, which k was fitted to: on dark
    8-bit 360x480x8 procedural bursts its photosites erred 5.3x (seed 4) and 3.3x (seed 5) their sigma_k
    (RMS), the lowest tenth 1.43x / 1.32x (1.00 / 1.03 bounded). Elsewhere the residuals' own variance
    stands (the noise model holds the prediction's error on fine textures, docs/method.md section 12c)."""
    if not noise:
        return
    n = len(frames)
    level = frames.mean(axis=0, dtype=np.float64)
    black = np.zeros(frames.shape[1:], np.float32)
    for frame in frames:  # one frame at a time: no (F, H, W, C) mask at 12 MP x 16
        black[frame <= 0] = 1.0
    for name, pick, _ in plane_views(burst.cfa, burst.channels):
        model = noise.get(name)
        if model is None:
            continue
        c = pick(confidence)
        marked = np.maximum(pick(black), c <= 0, dtype=np.float32)  # read black, or left unestimated
        near = (window_sum(marked, DARK_WINDOW) > 0) & (c > 0)
        if not near.any():
            continue
        lv = np.maximum(pick(level)[near], np.finfo(np.float32).tiny)
        bound = np.sqrt(np.maximum(model(lv), 0.0) / (n * lv**2))
        c[near] = np.minimum(c[near], confidence_from_sigma(bound)).astype(c.dtype)
