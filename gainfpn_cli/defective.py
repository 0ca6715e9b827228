"""A burst's defective photosites: found plane by plane (:mod:`solve.defects`), hot ones also from
a dark frame, left out of the solve, counted, and repaired in corrected frames.

A defect map is ``(H, W, C)`` uint8 like the frames: 0 healthy, else the kind's code
(:data:`solve.defects.KINDS`).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from .errors import EstimationError
from .geometry.planes import plane_views
from .metrics import MAD_TO_SIGMA
from .solve import defects as D
from .solve.repair import fill

#: A photosite of a dark frame this many robust standard deviations above its plane's median is
#: hot (its offset is at least that many times the dark frame's noise, which is at most the noise
#: of a lit frame). At 5, a Gaussian's tail holds 3e-7 of the healthy photosites.
Z_DARK = 5.0

#: Above this fraction of defective photosites in a plane the burst is refused: no sensor is that
#: broken, so the frames are not of one scene moving (a blank or corrupted frame, a wrong dark frame).
MAX_DEFECTIVE = 0.05


@dataclass(frozen=True)
class Found:
    """A burst's defect map ``(H, W, C)`` uint8 and each plane's readings' noise against level
    (plane name -> :class:`solve.noise.NoiseModel`, None where the search could test nothing)."""

    codes: np.ndarray
    noise: dict


def find(frames: np.ndarray, cfa: str | None, channels: tuple[str, ...], *, excluded: np.ndarray | None,
         exposures: np.ndarray, warp, saturation: float | None, dark_hot: np.ndarray | None = None,
         latent: bool = True, threads: int = 1) -> Found:
    """The defect map of a burst ``frames`` ``(F, H, W, C)`` (DN after black, reference first) and its
    planes' noise, ``warp`` its motion in frame pixels, ``excluded`` ``(F, H, W)`` the readings of
    moving objects, ``dark_hot`` ``(H, W, C)`` the hot photosites a dark frame shows (:func:`hot_in_dark`);
    ``latent``: a CFA's planes' likeliest hot photosites tested again (:mod:`solve.leftout`); each plane
    searched on ``threads`` threads (the same result on any number)."""
    if saturation is not None:  # a frame at a time: a mask of the stack's channels is 192 MB at 12 MP x 16
        clipped = np.empty(frames.shape[:-1], bool)
        for t, frame in enumerate(frames):
            np.any(frame >= saturation, axis=-1, out=clipped[t])
        if clipped.any():
            excluded = clipped if excluded is None else excluded | clipped
        del clipped
    codes = np.zeros(frames.shape[1:], np.uint8)
    noise = {}
    mask = None if excluded is None else np.broadcast_to(excluded[..., None], frames.shape)
    for name, pick, S in plane_views(cfa, channels):
        plane = pick(frames)
        out = pick(codes[None])[0]
        found = D.survey(plane, warp.conjugate(S), excluded=None if mask is None else pick(mask), exposures=exposures,
                         aperture=0.5 if cfa else 1.0, latent=latent, threads=threads)
        out[...], noise[name] = found.codes, found.noise
        if dark_hot is not None:
            out[(out == D.HEALTHY) & pick(dark_hot[None])[0]] = D.HOT
        fraction = float(np.mean(out > 0))
        if fraction > MAX_DEFECTIVE:
            raise EstimationError(f"{100 * fraction:.0f} % of the photosites of plane {name} read as defective "
                                  f"(more than {100 * MAX_DEFECTIVE:.0f} %): the frames do not show one scene "
                                  "moving (a blank or corrupted frame?) or the dark frame is not this sensor's")
    return Found(codes, noise)


#: Score of an offset in a photosite's readings against the scene solver's fitted scene past which it
#: is hot (:func:`offset_shown`): about N(0, 1) on healthy photosites, with heavier tails where the
#: model misfits. On 48 defect-free 240x320 paper bursts of 8 frames (the simulated scenes, on which
#: it was chosen, at most 5.67; ten photographs, 7.09) 4 of 3.4 million healthy ones scored above it
#: (docs/bench/defects.py model scores).
Z_MODEL_OFFSET = 6.0


def offset_shown(offsets: np.ndarray) -> np.ndarray:
    """The photosites of a plane whose readings carry an offset the scene solver's fitted scene tells
    from a gain (``offsets``: :func:`solve.scene.offset_scores`): hot ones the search before the
    solve missed, because its prediction of the scene (one or two other readings) is noisier; those
    whose k came out of the gain range (unestimated) too. Not asked of a CFA colour's plane, whose
    latent scene is still aliased (docs/limits.md)."""
    return offsets > Z_MODEL_OFFSET


def add_hot(codes: np.ndarray, hot: np.ndarray) -> None:
    """``codes`` with the healthy photosites marked in ``hot`` coded hot, in place."""
    codes[(codes == D.HEALTHY) & hot] = D.HOT


def hot_in_dark(dark: np.ndarray, cfa: str | None, channels: tuple[str, ...]) -> np.ndarray:
    """Hot photosites of a master dark frame ``(H, W, C)``, plane by plane, ``(H, W, C)`` bool: above
    the plane's median by :data:`Z_DARK` times its robust spread (read noise and dark signal
    nonuniformity)."""
    hot = np.zeros(dark.shape, bool)
    for _, pick, _ in plane_views(cfa, channels):
        plane = np.asarray(pick(dark[None])[0], np.float64)
        centre = float(np.median(plane))
        spread = MAD_TO_SIGMA * float(np.median(np.abs(plane - centre)))
        pick(hot[None])[0][...] = plane > centre + Z_DARK * max(spread, np.finfo(np.float32).tiny)
    return hot


@contextmanager
def repaired(frames: np.ndarray, codes: np.ndarray | None, cfa: str | None, channels: tuple[str, ...]):
    """``frames`` ``(F, H, W, C)`` with their defective photosites' readings replaced from their
    neighbours (:func:`repair`) while the block runs, then put back.

    In place, so the frames are held once (only the defects' readings are kept aside). Leaving
    the defects out of the solve instead would lose every sample whose interpolation kernel
    touches one: with Lanczos-4 (8x8), 8.6 % of them at a sensor's 0.14 % defects."""
    bad = None if codes is None else np.nonzero(codes)
    if bad is None or not len(bad[0]):
        yield frames
        return
    kept = frames[(slice(None),) + bad].copy()
    for t in range(len(frames)):
        frames[t] = repair(frames[t], codes, cfa, channels)
    try:
        yield frames
    finally:
        frames[(slice(None),) + bad] = kept


def leave_out(k: np.ndarray, confidence: np.ndarray, codes: np.ndarray, cfa: str | None,
              channels: tuple[str, ...]) -> None:
    """k = 1 and confidence 0 at the defects, in place; each plane's other estimated k scaled back
    to mean 1 (the gauge, which counted the defects' k)."""
    bad = codes > 0
    if not bad.any():
        return
    k[bad] = 1.0
    confidence[bad] = 0.0
    for _, pick, _ in plane_views(cfa, channels):
        kp, est = pick(k[None])[0], pick(confidence[None])[0] > 0
        if est.any():
            kp[est] /= np.float32(kp[est].mean(dtype=np.float64))


def counts(codes: np.ndarray) -> dict[str, int]:
    """Defective photosites by kind."""
    return {kind: int(np.count_nonzero(codes == code)) for kind, code in D.KINDS.items()}


def repair(frame: np.ndarray, codes: np.ndarray, cfa: str | None, channels: tuple[str, ...]) -> np.ndarray:
    """``frame`` ``(H, W, C)`` with its defective photosites replaced from the healthy neighbours
    of their plane (a CFA colour from its own colour's lattice)."""
    if not codes.any():
        return frame
    out = np.array(frame, np.float32)
    for _, pick, _ in plane_views(cfa, channels):
        view = pick(out[None])[0]
        view[...] = fill(view, pick(codes[None])[0] > 0)
    return out
