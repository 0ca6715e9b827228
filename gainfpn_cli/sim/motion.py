"""The simulated camera's motion: hand-held shake and pan as homographies, plus a rolling-shutter
wobble or a smooth distortion that no single warp explains."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.warps import project


@dataclass(frozen=True)
class Shake:
    """Hand-held camera motion relative to frame 0 (frame 0 is the identity)."""

    translation_px: float = 2.0  # sigma of the per-frame translation, px
    rotation_deg: float = 0.3  # sigma of the per-frame rotation about the centre
    drift_px: float = 0.0  # steady pan over the whole burst, px, in a random direction
    perspective: float = 0.0  # sigma of the projective terms, 1/px
    wobble_px: float = 0.0  # sigma of a rolling-shutter wobble's amplitude, px (no single warp explains it)
    wobble_cycles: float = 1.5  # its periods over the frame height
    distortion_px: float = 0.0  # sigma of a smooth 2-D distortion's amplitude per axis, px (parallax, lens)
    distortion_cycles: float = 1.0  # its periods over the frame's longer side


def shake_homographies(n_frames: int, shape: tuple[int, int], shake: Shake, rng: np.random.Generator) -> np.ndarray:
    """``H_t_ref`` for each frame: rotation about the centre, translation, drift."""
    h, w = shape
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    direction = rng.uniform(0, 2 * np.pi)
    out = np.empty((n_frames, 3, 3))
    out[0] = np.eye(3)
    for t in range(1, n_frames):
        angle = np.deg2rad(rng.normal(0.0, shake.rotation_deg))
        shift = rng.normal(0.0, shake.translation_px, size=2)
        shift += shake.drift_px * t / max(n_frames - 1, 1) * np.array([np.cos(direction), np.sin(direction)])
        c, s = np.cos(angle), np.sin(angle)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        to_origin = np.array([[1.0, 0.0, -centre[0]], [0.0, 1.0, -centre[1]], [0.0, 0.0, 1.0]])
        back = np.array([[1.0, 0.0, centre[0] + shift[0]], [0.0, 1.0, centre[1] + shift[1]], [0.0, 0.0, 1.0]])
        persp = np.eye(3)
        persp[2, :2] = rng.normal(0.0, shake.perspective, size=2)
        out[t] = back @ rot @ persp @ to_origin
    return out


def wave_parameters(n_frames: int, shape: tuple[int, int], shake: Shake, rng: np.random.Generator) -> np.ndarray | None:
    """Per frame and wave ``(axis, amplitude px, angle rad, phase rad, wavelength px)``, or None without waves.

    Frame t sees reference point ``p`` at ``q = H_t p + shift(q)``, the sum
    over waves of ``A sin(2 pi (q_x cos a + q_y sin a) / L + phi)`` along
    ``axis`` (0: x, 1: y). A rolling-shutter wobble is one horizontal wave
    down the rows (``a = pi / 2``), as a shutter that reads row ``q_y`` at
    its own time records a vibrating camera; a distortion is one wave per
    axis in random directions, a smooth 2-D stand-in for parallax or a
    change of lens distortion. The reference has none.
    """
    h, w = shape
    waves = []
    if shake.wobble_px > 0:
        wobble = np.zeros((n_frames, 5))
        wobble[:, 2], wobble[:, 4] = np.pi / 2, h / shake.wobble_cycles
        wobble[1:, 1] = rng.normal(0.0, shake.wobble_px, n_frames - 1)
        wobble[1:, 3] = rng.uniform(0, 2 * np.pi, n_frames - 1)
        waves.append(wobble)
    if shake.distortion_px > 0:
        for axis in (0, 1):
            wave = np.zeros((n_frames, 5))
            wave[:, 0], wave[:, 4] = axis, max(h, w) / shake.distortion_cycles
            wave[1:, 1] = rng.normal(0.0, shake.distortion_px, n_frames - 1)
            wave[1:, 2] = rng.uniform(0, np.pi, n_frames - 1)
            wave[1:, 3] = rng.uniform(0, 2 * np.pi, n_frames - 1)
            waves.append(wave)
    return np.stack(waves, axis=1) if waves else None


def wave_shift(waves: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The shift ``(dx, dy)`` of one frame's ``waves`` ``(K, 5)`` at frame point ``(x, y)``."""
    out = [np.zeros(np.broadcast(x, y).shape), np.zeros(np.broadcast(x, y).shape)]
    for axis, amplitude, angle, phase, wavelength in waves:
        out[int(axis)] += amplitude * np.sin(2 * np.pi * (x * np.cos(angle) + y * np.sin(angle)) / wavelength + phase)
    return out[0], out[1]


def margin_px(homographies: np.ndarray, shape: tuple[int, int]) -> int:
    """Sensor pixels the scene must extend past the reference view."""
    h, w = shape
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1]]).T
    worst = 0.0
    for H in homographies:
        p = project(np.linalg.inv(H), corners)
        worst = max(worst, float(np.max(-p)), float(np.max(p[0] - w)), float(np.max(p[1] - h)))
    return int(np.ceil(worst)) + 4
