"""A latent scene shared by the colours of a mosaic? (docs/limits.md, "The scene solver")

    python docs/bench/shared_scene.py [SCENES [SEED]]   # default: procedural,coffee 1

640x480x8 12-bit RGGB bursts (``raw12``: 1 % pixel gain FPN, 75 % exposure), with noise and
without (16-bit, no shot or read noise: the model error alone). Each is estimated three ways:
``accurate`` (the accurate solver plane by plane, what ``auto`` runs on a mosaic), ``scene``
(the scene solver plane by plane) and ``shared`` (the scene solver on the whole mosaic as one
monochrome plane: one latent scene for every colour, after each photosite was divided by its
colour's local level against the mosaic's, Gaussian means of the frames' mean over 8 plane px and
16 px; a smooth colour ratio, fixed to the sensor). SCENES are built-in scenes or scikit-image's
colour sample photographs (``coffee``, ``chelsea``, ...; not a dependency of gainfpn: ``pip
install scikit-image``), linearised with a 2.2 power. One JSON line per burst and way: the
residual gain FPN of each plane (16 plane px in from the border) against the FPN it had, %, and
the share of the residual's variance in its band wider than about 8 plane px.
About 6 minutes for the default.
"""

import dataclasses
import json
import sys
import time

import numpy as np
from scipy.ndimage import gaussian_filter

from gainfpn_cli import api
from gainfpn_cli.sim.scenes import read_scene
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst

PLANES = {"R": (0, 0), "G1": (0, 1), "G2": (1, 0), "B": (1, 1)}
MARGIN = 16  # plane px left out at the border, where trajectories leave the frame
LEVEL_SIGMA = 8.0  # plane px of the Gaussian means a colour's level is taken from


def scene_of(name):
    """A built-in scene by name, or scikit-image's sample photograph read as ``gainfpn simulate --scene
    FILE`` reads it (:func:`read_scene`: linear, gamma 2.2)."""
    if name in ("procedural", "dead-leaves"):
        return name
    from pathlib import Path

    import skimage.data

    return read_scene(next(Path(skimage.data.data_dir).glob(name + ".*")))


def colour_levels(frames):
    """Each photosite's colour level against the mosaic's: the Gaussian mean of its plane of the
    frames' mean over the Gaussian mean of the whole mosaic's (twice as wide, in photosites)."""
    mean = frames.mean(axis=0)
    mosaic = gaussian_filter(mean, 2 * LEVEL_SIGMA)
    level = np.empty_like(mean)
    for y, x in PLANES.values():
        level[y::2, x::2] = gaussian_filter(mean[y::2, x::2], LEVEL_SIGMA) / mosaic[y::2, x::2]
    return level


def residuals(k, gain):
    """Per plane: the residual gain FPN and the FPN it had, %, and the share of the residual's variance
    that a Gaussian of 4 plane px keeps (its band wider than about 8 plane px)."""
    out = {}
    for name, (y, x) in PLANES.items():
        left, had = k[y::2, x::2] * gain[y::2, x::2], gain[y::2, x::2]
        error = left / left[MARGIN:-MARGIN, MARGIN:-MARGIN].mean() - 1
        inner = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
        low = gaussian_filter(error, 4.0)[inner]
        had = had[inner]
        out[name] = [round(100 * float(np.std(error[inner])), 3), round(100 * float(np.std(had / had.mean())), 3),
                     round(float(np.var(low) / np.var(error[inner])), 2)]
    return out


def run(scene, seed, noise):
    sensor = PRESETS["raw12"]
    if not noise:
        sensor = dataclasses.replace(sensor, shot_noise=False, read_noise_e=0.0, adc_bits=16)
    b = simulate_burst(shape=(480, 640), n_frames=8, sensor=sensor, exposure=0.75, scene=scene_of(scene), seed=seed)
    frames = b.frames.astype(np.float32) - sensor.black_level
    saturation = float(sensor.white_level - sensor.black_level)
    for way in ("accurate", "scene", "shared"):
        t = time.perf_counter()
        if way == "shared":
            level = colour_levels(frames)
            e = api.estimate(frames / level, saturation=saturation / float(level.min()), **{"solver.method": "scene"})
        else:
            e = api.estimate(frames, cfa="RGGB", saturation=saturation, **{"solver.method": way})
        print(json.dumps({"scene": scene, "seed": seed, "noise": noise, "way": way, "status": e.report.status,
                          "seconds": round(time.perf_counter() - t, 1),
                          "residual_had_percent_low_share": residuals(e.k[..., 0], b.gain)}), flush=True)


if __name__ == "__main__":
    scenes = sys.argv[1].split(",") if len(sys.argv) > 1 else ["procedural", "coffee"]
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    for name in scenes:
        for noise in (True, False):
            run(name, seed, noise)
