"""Seeded synthetic bursts with known truth.

A scene (a built-in texture, or a user image) is viewed through a hand-held
camera: frame ``t`` sees reference-frame point ``p`` at ``H_t_ref @ p``. Each
pixel integrates the scene over its area (``supersample**2`` sub-samples of a
cubic-interpolated scene raster), then the sensor of docs/method.md section 1
turns light into counts:

    electrons ~ Poisson(a * e_ideal) + Normal(0, read_noise)
    counts    = round(clip(electrons, 0, full_well) * dn_per_e) + black

with the gain ``a`` = pixel x column x even/odd-row components. Every random
source is its own child of one ``SeedSequence``: changing the noise level
does not change the scene, motion or gains.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

CFA_CHANNEL = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class Sensor:
    """Sensor and ADC; defaults are the paper's sensor (docs/method.md section 4)."""

    conversion_gain_uv: float = 32.5  # uV per electron
    swing_v: float = 1.0  # output swing, V
    read_noise_e: float = 50.0  # electrons RMS
    adc_bits: int = 8
    black_level: int = 0  # DN added before the ADC clips
    fpn_pixel: float = 0.05  # sigma of the per-pixel gain
    fpn_column: float = 0.0  # sigma of the per-column gain
    fpn_row: float = 0.0  # sigma of the even/odd-row gain
    cfa: str | None = None  # 2x2 layout such as "RGGB", or None (monochrome)
    shot_noise: bool = True  # Poisson photon noise (off only for tests of the model)

    @property
    def full_well_e(self) -> float:
        return self.swing_v / (self.conversion_gain_uv * 1e-6)

    @property
    def white_level(self) -> int:
        return 2**self.adc_bits - 1

    @property
    def dn_per_e(self) -> float:
        return self.white_level / self.full_well_e


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


#: Named sensors: the paper's, and a 12-bit RGGB camera for DNG bursts.
PRESETS = {
    "paper": Sensor(),
    "raw12": Sensor(conversion_gain_uv=50.0, swing_v=1.0, read_noise_e=3.0, adc_bits=12, black_level=256,
                    fpn_pixel=0.01, cfa="RGGB"),
}


@dataclass(frozen=True)
class Burst:
    """A simulated burst and its truth.

    Attributes
    ----------
    frames : ndarray of uint16, shape (F, H, W)
        ADC counts, black level included.
    gain : ndarray of float32, shape (H, W)
        The true gain ``a`` (the correction is ``k = 1 / a`` up to a gauge).
    ideal : ndarray of float32, shape (F, H, W)
        Noise-free, FPN-free frames in DN after black level.
    homographies : ndarray of float64, shape (F, 3, 3)
        ``H_t_ref``: reference (frame 0) pixel coordinates to frame t.
    sensor : Sensor
    moving : ndarray of bool, shape (F, H, W), optional
        Pixels of each frame that see some of the moving object (in that
        frame's own coordinates); None without one.
    waves : ndarray, shape (F, K, 5), optional
        Motion no single warp explains (see :func:`wave_parameters`); None
        without any. :meth:`positions` includes it.
    object_offsets : ndarray, shape (F, 2), optional
        The moving object's own displacement (reference px) in each frame:
        frame t sees the object's reference point ``p`` at ``H_t (p + o_t)``.
    exposures : ndarray, shape (F,), optional
        Each frame's exposure relative to the reference's (1); None if all
        are exposed alike.
    """

    frames: np.ndarray
    gain: np.ndarray
    ideal: np.ndarray
    homographies: np.ndarray
    sensor: Sensor
    moving: np.ndarray | None = None
    waves: np.ndarray | None = None
    object_offsets: np.ndarray | None = None
    exposures: np.ndarray | None = None

    @property
    def saturation(self) -> int:
        """Largest count above black the ADC can give."""
        return self.sensor.white_level - self.sensor.black_level

    def positions(self, t: int) -> np.ndarray:
        """Where frame t sees every reference pixel: ``(H, W, 2)`` float64 ``(x, y)``, waves included."""
        from ..geometry.warps import positions_from_homography

        pos = positions_from_homography(self.homographies[t], self.frames.shape[1:])
        if self.waves is None or not np.any(self.waves[t, :, 1]):
            return pos
        q = pos.copy()
        for _ in range(WAVE_ITERATIONS):  # q = H p + shift(q): a contraction for gentle waves
            q = pos + np.stack(wave_shift(self.waves[t], q[..., 0], q[..., 1]), axis=-1)
        return q

    def object_positions(self, t: int) -> np.ndarray:
        """Where frame t sees every reference pixel if it were on the moving object: ``H_t (p + o_t)``."""
        from ..geometry.warps import positions_from_homography

        T = np.eye(3)
        T[:2, 2] = self.object_offsets[t]
        return positions_from_homography(self.homographies[t] @ T, self.frames.shape[1:])


#: Fixed-point iterations of ``q = H p + shift(q)`` in :meth:`Burst.positions`;
#: each shrinks the error by the shift's slope (2 pi A / L, 0.04 for a 1 px
#: wave of 160 px): far below float precision after these.
WAVE_ITERATIONS = 30


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


#: Built-in scenes, by name. ``dead-leaves`` uses a smallest leaf of 3 sensor
#: pixels, chosen so that the paper's published form gives about its
#: published ratio (2.8x; measured medians 2.2x on 120x160 and 2.6x on
#: 240x320 bursts). The other figures of docs/method.md section 5, measured there
#: on a real photograph (global Lanczos solve 15x), then follow without
#: further tuning (accurate mode, 120x160: median 16x).
#: ``procedural`` is smoother (multi-scale noise and shapes of >= 1.5 px).
SCENES = ("procedural", "dead-leaves")
DEAD_LEAVES_MIN_PX = 3.0


def gain_pattern(shape: tuple[int, int], sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """True gain ``a`` = (1 + pixel) * (1 + column) * (1 + even/odd row), float32."""
    h, w = shape
    pixel = 1.0 + sensor.fpn_pixel * rng.standard_normal(shape)
    column = 1.0 + sensor.fpn_column * rng.standard_normal(w)
    row_pair = 1.0 + sensor.fpn_row * rng.standard_normal(2)
    row = row_pair[np.arange(h) % 2]
    return np.clip(pixel * column[None, :] * row[:, None], 0.05, None).astype(np.float32)


def _margin(homographies: np.ndarray, shape: tuple[int, int]) -> int:
    """Sensor pixels the scene must extend past the reference view."""
    h, w = shape
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [-0.5, h - 0.5, 1], [w - 0.5, h - 0.5, 1]]).T
    worst = 0.0
    for H in homographies:
        p = np.linalg.inv(H) @ corners
        p = p[:2] / p[2]
        worst = max(worst, float(np.max(-p)), float(np.max(p[0] - w)), float(np.max(p[1] - h)))
    return int(np.ceil(worst)) + 4


def render(scene: np.ndarray, H: np.ndarray, shape: tuple[int, int], *, scale: int, margin: int, supersample: int,
           waves: np.ndarray | None = None) -> np.ndarray:
    """Area-integrate the scene as seen by a frame with homography ``H`` (ref -> frame).

    Scene raster pixel ``j`` has its centre at reference coordinate
    ``(j + 0.5) / scale - 0.5 - margin``. With ``waves`` (see
    :func:`wave_parameters`) the frame sees reference point ``p`` at
    ``q = H p + shift(q)``, so each sample ``q`` reads ``p = H^-1 (q - shift(q))``.
    """
    import cv2

    h, w = shape
    Hinv = np.linalg.inv(H)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    acc = np.zeros((h, w) + scene.shape[2:], np.float64)
    steps = (np.arange(supersample) + 0.5) / supersample - 0.5
    for dv in steps:
        for du in steps:
            X, Y = xs + du, ys + dv
            if waves is not None:
                dx, dy = wave_shift(waves, X, Y)
                X, Y = X - dx, Y - dy
            px, py = _apply(Hinv, X, Y)
            map_x = ((px + margin + 0.5) * scale - 0.5).astype(np.float32)
            map_y = ((py + margin + 0.5) * scale - 0.5).astype(np.float32)
            acc += cv2.remap(scene, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(acc / supersample**2, 0.0, None)


def _apply(H: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    den = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / den, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / den


def simulate_burst(
    *,
    shape: tuple[int, int] = (240, 320),
    n_frames: int = 8,
    sensor: Sensor = PRESETS["paper"],
    shake: Shake = Shake(),
    exposure: float = 0.75,
    scene: np.ndarray | str = "procedural",
    supersample: int = 4,
    optics_sigma_px: float = 0.0,
    moving_object: float = 0.0,
    parallax: float = 0.0,
    exposure_jitter: float = 0.0,
    seed: int = 0,
) -> Burst:
    """Simulate a hand-held burst with known gain, motion and ideal frames.

    Parameters
    ----------
    shape : (int, int)
        ``(H, W)`` of the frames, photosites.
    exposure : float
        Scene value 1.0 gives ``exposure * full_well`` electrons.
    scene : ndarray or str
        Linear scene raster in [0, 1], ``(h, w)`` or ``(h, w, 3)``, resized
        to cover the burst; or the name of a built-in scene (:data:`SCENES`).
    supersample : int
        Sub-samples per pixel side for area integration.
    optics_sigma_px : float
        Sigma (px) of a Gaussian lens point-spread function applied to the
        scene before the pixels integrate it; 0 is a perfect lens.
    moving_object : float
        Fraction of the frame covered by a textured disk that moves on its
        own (about 2 px per frame, in a random direction, plus a jitter of
        1 px) on top of the camera's motion; 0 for none.
    parallax : float
        With ``moving_object``: the disk is instead a nearer plane that does
        not move on its own, its image displaced ``1 + parallax`` times as
        far as the background's at its centre (the parallax of a camera that
        translates; 0.5: half as near again).
    exposure_jitter : float
        Sigma of the log of each frame's exposure relative to the
        reference's (auto-exposure steps, flickering light); 0: all alike.
    """
    h, w = shape
    if h < 2 or w < 2 or n_frames < 1:
        raise ValueError(f"need frames of at least 2x2 and one frame, got shape {shape}, {n_frames} frames")
    if sensor.cfa is not None and (len(sensor.cfa) != 4 or set(sensor.cfa) - set(CFA_CHANNEL)):
        raise ValueError(f"sensor.cfa must be a 2x2 RGB layout such as RGGB, got {sensor.cfa!r}")
    # a fifth stream for the exposures: the first four (and every burst without jitter) stay as they were
    rng_scene, rng_motion, rng_gain, rng_noise, rng_exposure = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5))
    exposures = np.exp(exposure_jitter * rng_exposure.standard_normal(n_frames)) if exposure_jitter > 0 else None
    if exposures is not None:
        exposures[0] = 1.0
    homographies = shake_homographies(n_frames, shape, shake, rng_motion)
    waves = wave_parameters(n_frames, shape, shake, rng_motion)
    margin = _margin(homographies, shape) + (0 if waves is None else int(np.ceil(np.abs(waves[:, :, 1]).sum(1).max())))
    scale = 2
    raster_shape = ((h + 2 * margin) * scale, (w + 2 * margin) * scale)
    colour = sensor.cfa is not None
    if isinstance(scene, str) and scene == "procedural":
        raster = procedural_scene(raster_shape, rng_scene, colour=colour)
    elif isinstance(scene, str) and scene == "dead-leaves":
        raster = dead_leaves(raster_shape, rng_scene, r_min=DEAD_LEAVES_MIN_PX * scale, colour=colour)
    elif isinstance(scene, str):
        raise ValueError(f"scene must be an image or one of {', '.join(SCENES)}, got {scene!r}")
    else:
        raster = _fit_scene(np.asarray(scene, np.float32), raster_shape, colour=colour)
    if optics_sigma_px > 0:
        import cv2

        raster = cv2.GaussianBlur(raster, (0, 0), optics_sigma_px * scale, borderType=cv2.BORDER_REFLECT)
    gain = gain_pattern(shape, sensor, rng_gain)
    frames = np.empty((n_frames, h, w), np.uint16)
    ideal = np.empty((n_frames, h, w), np.float32)
    obj = _moving_object(raster, moving_object, n_frames, shape, scale, margin,
                         np.random.default_rng(rng_scene.integers(2**63)), homographies if parallax else None, parallax)
    moving = None if obj is None else np.zeros((n_frames, h, w), bool)
    full_scale_dn = float(sensor.white_level - sensor.black_level)
    for t in range(n_frames):
        view = dict(scale=scale, margin=margin, supersample=supersample, waves=None if waves is None else waves[t])
        light = render(raster, homographies[t], shape, **view)
        if obj is not None:  # the object is recorded by the same (rolling) shutter
            texture, alpha, offsets = obj
            H_obj = homographies[t] @ np.array([[1.0, 0, offsets[t, 0]], [0, 1.0, offsets[t, 1]], [0, 0, 1.0]])
            cover = render(alpha, H_obj, shape, **view)
            seen = render(texture, H_obj, shape, **view)
            cover = np.clip(cover, 0.0, 1.0).reshape(cover.shape + (1,) * (light.ndim - cover.ndim))
            light = light * (1.0 - cover) + seen
            moving[t] = cover.reshape(shape) > 1e-3
        if colour:
            light = _mosaic(light, sensor.cfa)
        electrons = exposure * (1.0 if exposures is None else exposures[t]) * sensor.full_well_e * light
        ideal[t] = np.minimum(electrons * sensor.dn_per_e, full_scale_dn)
        collected = rng_noise.poisson(gain * electrons) if sensor.shot_noise else gain * electrons
        signal = collected + rng_noise.normal(0.0, sensor.read_noise_e, shape)
        counts = np.floor(np.clip(signal, 0.0, sensor.full_well_e) * sensor.dn_per_e + 0.5) + sensor.black_level
        frames[t] = np.clip(counts, 0, sensor.white_level)
    return Burst(frames=frames, gain=gain, ideal=ideal, homographies=homographies, sensor=sensor, moving=moving,
                 waves=waves, object_offsets=None if obj is None else obj[2], exposures=exposures)


def _moving_object(raster, fraction, n_frames, shape, scale, margin, rng, homographies=None, parallax=0.0):
    """``(texture * alpha, alpha, offsets)`` of a disk covering ``fraction`` of the frame, or None.

    ``offsets[t]`` is the object's own displacement (reference px) in frame
    t; with ``homographies``, ``parallax`` times the background's at its centre.
    """
    import cv2

    if fraction <= 0:
        return None
    h, w = shape
    radius = np.sqrt(fraction * h * w / np.pi)
    centre = rng.uniform([0.3 * w, 0.3 * h], [0.7 * w, 0.7 * h])
    alpha = np.zeros(raster.shape[:2], np.float32)
    fixed = 16
    cx, cy = ((centre + margin + 0.5) * scale - 0.5) * fixed
    cv2.circle(alpha, (int(cx), int(cy)), int(radius * scale * fixed), 1.0, -1, lineType=cv2.LINE_AA, shift=4)
    texture = dead_leaves(raster.shape[:2], rng, r_min=DEAD_LEAVES_MIN_PX * scale, colour=raster.ndim == 3)
    alpha_c = alpha if raster.ndim == 2 else alpha[:, :, None]
    heading = rng.uniform(0, 2 * np.pi)
    steps = np.arange(n_frames)[:, None] * 2.0 * np.array([np.cos(heading), np.sin(heading)])
    offsets = steps + rng.normal(0.0, 1.0, (n_frames, 2))
    if homographies is not None:
        centred = np.array([*centre, 1.0])
        offsets = np.array([parallax * ((H @ centred)[:2] / (H @ centred)[2] - centre) for H in homographies])
    offsets[0] = 0.0
    return texture * alpha_c, alpha, offsets


def _mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for position, colour in enumerate(cfa):
        dy, dx = divmod(position, 2)
        out[dy::2, dx::2] = rgb[dy::2, dx::2, CFA_CHANNEL[colour]]
    return out


def _fit_scene(image: np.ndarray, shape: tuple[int, int], *, colour: bool) -> np.ndarray:
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


def with_overrides(sensor: Sensor, **changes) -> Sensor:
    """``sensor`` with the given fields replaced (None values are ignored)."""
    return dataclasses.replace(sensor, **{k: v for k, v in changes.items() if v is not None})
