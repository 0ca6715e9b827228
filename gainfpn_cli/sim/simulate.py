"""Seeded synthetic bursts with known truth.

A scene (a built-in texture, or a user image) is viewed through a hand-held
camera: frame ``t`` sees reference-frame point ``p`` at ``H_t_ref @ p``. Each
pixel integrates the scene over its area (``supersample**2`` sub-samples of a
cubic-interpolated scene raster), then the sensor of docs/method.md section 1
turns light into counts:

    electrons ~ Poisson(a * e_ideal) + Normal(0, read_noise)
    counts    = round(clip(electrons, 0, full_well) * dn_per_e) + black

with the gain ``a`` = pixel x column x even/odd-row components. Defective
photosites (``defects``) are drawn in :data:`DEFECT_SHARES`: a hot one
collects a dark-current offset on top (log-uniform in :data:`HOT_OFFSET_NOISE`
times its temporal noise in the reference frame), a dead one no light, a
stuck one reads one count in every frame. Every random source is its own
child of one ``SeedSequence``: changing the noise level does not change the
scene, motion or gains, and the defects change no healthy photosite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.warps import homography_xy, project
from ..solve.defects import DEAD, HOT, KINDS, STUCK
from .motion import Shake, margin_px, shake_homographies, wave_parameters, wave_shift
from .scenes import SCENES, dead_leaves, fit_scene, procedural_scene
from .sensor import CFA_CHANNEL, PRESETS, Sensor, gain_pattern

#: Fixed-point iterations of ``q = H p + shift(q)`` in :meth:`Burst.positions`;
#: each shrinks the error by the shift's slope (2 pi A / L, 0.04 for a 1 px
#: wave of 160 px): far below float precision after these.
WAVE_ITERATIONS = 30

DEAD_LEAVES_MIN_PX = 3.0

#: Shares of the kinds among simulated defective photosites: a sensor's 0.1 % hot, 0.02 % dead
#: and 0.02 % stuck pixels.
DEFECT_SHARES = {"hot": 0.70, "dead": 0.15, "stuck": 0.15}
#: A hot photosite's offset, in units of its temporal noise in the reference frame: drawn
#: log-uniformly in this range (the issue's threshold of a hot pixel is 5).
HOT_OFFSET_NOISE = (5.0, 50.0)


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
    defects : ndarray of uint8, shape (H, W), optional
        Defective photosites by kind (:data:`solve.defects.KINDS`, 0 healthy);
        None without any.
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
    defects: np.ndarray | None = None

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
            px, py = homography_xy(Hinv, X, Y)
            map_x = ((px + margin + 0.5) * scale - 0.5).astype(np.float32)
            map_y = ((py + margin + 0.5) * scale - 0.5).astype(np.float32)
            acc += cv2.remap(scene, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(acc / supersample**2, 0.0, None)


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
    defects: float = 0.0,
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
    defects : float
        Fraction of photosites that are defective (hot, dead, stuck in
        :data:`DEFECT_SHARES`); 0 for none.
    """
    h, w = shape
    if h < 2 or w < 2 or n_frames < 1:
        raise ValueError(f"need frames of at least 2x2 and one frame, got shape {shape}, {n_frames} frames")
    if sensor.cfa is not None and (len(sensor.cfa) != 4 or set(sensor.cfa) - set(CFA_CHANNEL)):
        raise ValueError(f"sensor.cfa must be a 2x2 RGB layout such as RGGB, got {sensor.cfa!r}")
    if not 0.0 <= defects < 1.0:
        raise ValueError(f"defects must be a fraction in [0, 1), got {defects}")
    # a fifth stream for the exposures and a sixth for the defects: the first ones (and every burst
    # without jitter or defects) stay as they were
    rng_scene, rng_motion, rng_gain, rng_noise, rng_exposure, rng_defect = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6))
    exposures = np.exp(exposure_jitter * rng_exposure.standard_normal(n_frames)) if exposure_jitter > 0 else None
    if exposures is not None:
        exposures[0] = 1.0
    homographies = shake_homographies(n_frames, shape, shake, rng_motion)
    waves = wave_parameters(n_frames, shape, shake, rng_motion)
    margin = margin_px(homographies, shape) + (0 if waves is None else int(np.ceil(np.abs(waves[:, :, 1]).sum(1).max())))
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
        raster = fit_scene(np.asarray(scene, np.float32), raster_shape, colour=colour)
    if optics_sigma_px > 0:
        import cv2

        raster = cv2.GaussianBlur(raster, (0, 0), optics_sigma_px * scale, borderType=cv2.BORDER_REFLECT)
    gain = gain_pattern(shape, sensor, rng_gain)
    frames = np.empty((n_frames, h, w), np.uint16)
    ideal = np.empty((n_frames, h, w), np.float32)
    obj = _moving_object(raster, moving_object, n_frames, shape, scale, margin,
                         np.random.default_rng(rng_scene.integers(2**63)), homographies if parallax else None, parallax)
    moving = None if obj is None else np.zeros((n_frames, h, w), bool)
    kinds = _defect_kinds(shape, defects, rng_defect) if defects > 0 else None
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
        if kinds is not None:  # after the healthy draws, from a stream of its own
            if t == 0:  # the reference frame sets each hot photosite's offset, and each stuck one's reading
                noise = np.sqrt(gain * electrons + sensor.read_noise_e**2)
                hot_offset = np.where(kinds == HOT, noise * np.exp(rng_defect.uniform(
                    *np.log(HOT_OFFSET_NOISE), shape)), 0.0)
                stuck_at = rng_defect.integers(sensor.black_level, sensor.white_level + 1, shape)
            dark = rng_defect.poisson(hot_offset) if sensor.shot_noise else hot_offset
            collected = np.where(kinds == DEAD, 0.0, collected + dark)
        signal = collected + rng_noise.normal(0.0, sensor.read_noise_e, shape)
        counts = np.floor(np.clip(signal, 0.0, sensor.full_well_e) * sensor.dn_per_e + 0.5) + sensor.black_level
        frames[t] = np.clip(counts, 0, sensor.white_level)
        if kinds is not None:
            frames[t][kinds == STUCK] = stuck_at[kinds == STUCK]
    return Burst(frames=frames, gain=gain, ideal=ideal, homographies=homographies, sensor=sensor, moving=moving,
                 waves=waves, object_offsets=None if obj is None else obj[2], exposures=exposures, defects=kinds)


def _defect_kinds(shape: tuple[int, int], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Kind of every photosite (:data:`solve.defects.KINDS`): ``fraction`` of them defective,
    in :data:`DEFECT_SHARES`, at distinct random places."""
    size = shape[0] * shape[1]
    count = int(round(fraction * size))
    places = rng.choice(size, count, replace=False)
    kinds = np.zeros(size, np.uint8)
    start = 0
    for i, (name, share) in enumerate(DEFECT_SHARES.items()):
        n = count - start if i == len(DEFECT_SHARES) - 1 else int(round(share * count))  # the last: the rest
        kinds[places[start:start + n]] = KINDS[name]
        start += n
    return kinds.reshape(shape)


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
        offsets = np.array([parallax * (project(H, centred[:, None])[:, 0] - centre) for H in homographies])
    offsets[0] = 0.0
    return texture * alpha_c, alpha, offsets


def _mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for position, colour in enumerate(cfa):
        dy, dx = divmod(position, 2)
        out[dy::2, dx::2] = rgb[dy::2, dx::2, CFA_CHANNEL[colour]]
    return out
