"""How far the hot photosites the search misses are its scene prediction's fault, and how far a
better prediction of the scene from the burst could go.

    python docs/bench/hot_ceiling.py                 # every row (about 40 minutes)
    python docs/bench/hot_ceiling.py raw12 dead-leaves 0.75
    python docs/bench/hot_ceiling.py zalias raw12 dead-leaves 0.75   # shipped, by a detectability that counts aliasing
    python docs/bench/hot_ceiling.py latent raw12 dead-leaves 0.75   # the latent scene's test with its scene replaced

Per sensor, scene and exposure (8 frames, two 240x320 bursts with 0.5 % defects, true motion):
the share of the hot photosites that :func:`solve.defects.detect` flags, binned by
``sim.truth.hot_offset_z`` (how plainly the offset shows with the scene known), when the two
predictions of the scene it tests each photosite against (:mod:`solve.predict`) are

* ``shipped``: as they are, from the readings;
* ``noise-free``: the same two predictions made from the noise-free frames (their error is then the
  aliasing's and the interpolation's alone);
* ``latent``: a latent scene at 3x the plane's pitch (the scene model of :mod:`solve.scenemodel`,
  each photosite's box the plane's pitch wide, or half of it on a CFA colour's plane)
  fitted to the noise-free readings of the *other* photosites (16 folds, each a 4x4-periodic
  sixteenth left out in every frame) and rendered at the left-out ones: the best prediction
  tried that the plane's other readings give;
* ``latent, noisy``: the same fitted to the readings (noise, FPN, defects), flagged with the
  shipped search's flags added;
* ``truth``: the scene itself.

and, for each, the healthy photosites flagged on the same two bursts without defects.

``zalias``: the shipped search's share (seeds 0-1 and 2-3) binned both by ``hot_offset_z`` and by the same
detectability with each frame's scene known only to within the ``latent`` (noise-free) prediction's
error there: what a detector that predicted the scene as well as the plane's own samples allow could
show.

The ``latent`` command: the shipped search (seeds 0-1 and 2-3) with the scene that the latent scene's test of a
CFA colour's plane (:mod:`solve.leftout`) scores the suspects against replaced by

* ``noise-free``: the same fit (the same suspects and control left out) of the ideal readings (no
  noise, no gain FPN, no defects);
* ``cross-colour``: the shipped fit's rendering, corrected in each frame by the other colours as the
  simulator saw them at each photosite, noise-free (the green light at a red or blue photosite, red
  plus blue at a green one): in each 3x3 window of the plane the rendering fitted as a line of that
  light, evaluated at the window's centre (the edges placed where the other colours have them), over
  the readings the fit sees;
* ``the scene``: the noise-free frames themselves.
"""
import sys
from contextlib import contextmanager

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2]))
from gainfpn_cli.geometry.planes import plane_views
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim import simulate as sim
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import hot_offset_z
from gainfpn_cli.solve import defects as D
from gainfpn_cli.solve import leftout as L
from gainfpn_cli.solve import predict as P
from gainfpn_cli.solve.scene import SceneOptions, prepare
from gainfpn_cli.solve.scenemodel import fit_tile
from gainfpn_cli.solve.tiling import power_of_two_scale

EDGES = np.array([0, 4, 6, 10, 20, 40, np.inf])
#: Left-out pattern of the latent scene's folds (photosites (i % FOLD, j % FOLD) together).
FOLD = 4


def everywhere(t, frame):
    return np.ones(frame.shape, bool)


def left_out_rendering(frames, warp, gain_prior, aperture):
    """Each reading's ``B W_t S`` of a latent scene fitted without its photosite (FOLD^2 fits)."""
    frames = np.ascontiguousarray(frames, np.float32)
    _, h, w = frames.shape
    options = SceneOptions(scale=3, aperture=aperture, tile=max(h, w), halo=0, refine_frames=False, gain_prior=gain_prior)
    unit = power_of_two_scale(frames)
    out = np.zeros(frames.shape, np.float32)
    rows, cols = np.mgrid[:h, :w]
    fold = (rows % FOLD) * FOLD + cols % FOLD
    for k in range(FOLD * FOLD):
        out_k = np.broadcast_to(fold == k, frames.shape)
        (tile,) = prepare(dict(frames=frames, motion=warp, excluded=out_k), options)
        fit = fit_tile(tile)
        out[out_k] = (np.asarray(fit.predicted).reshape(frames.shape) * unit)[out_k]
    return out


@contextmanager
def predictions(median, nearest):
    """The search's two predictions of the scene replaced by ``median`` and ``nearest`` ``(F, H, W)``
    (where the shipped ones know the scene at all: the same readings are tested)."""
    shipped_scene, shipped_nearest = D.scene_along, D.nearest_along

    def scene_along(frames, good, warp, threads=1):
        _, valid, from_frames = shipped_scene(frames, good, warp, threads=threads)
        return median, valid, from_frames

    def nearest_along(frames, good, warp, threads=1):
        _, valid = shipped_nearest(frames, good, warp, threads=threads)
        return nearest, valid

    D.scene_along, D.nearest_along = scene_along, nearest_along
    try:
        yield
    finally:
        D.scene_along, D.nearest_along = shipped_scene, shipped_nearest


def replaced(mode, ideal, plane, warp, aperture):
    """The two predictions ``mode`` puts in the shipped ones' place (see the module)."""
    if mode == "noise-free":
        return P.scene_along(ideal, everywhere, warp)[0], P.nearest_along(ideal, everywhere, warp)[0]
    if mode == "latent":
        return (left_out_rendering(ideal, warp, 1e-3, aperture),) * 2
    if mode == "latent, noisy":
        return (left_out_rendering(plane, warp, 0.05, aperture),) * 2
    return ideal, ideal  # truth


def codes_of(b, sensor, mode):
    frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
    warp = GlobalWarp(b.homographies)
    codes = np.zeros(frames.shape[1:3], np.uint8)
    aperture = 1.0 if sensor.cfa is None else 0.5
    for _, pick, S in plane_views(sensor.cfa, ("Y",)):
        ideal = np.ascontiguousarray(pick(b.ideal[..., None]), np.float32)
        plane, conjugate = pick(frames), warp.conjugate(S)
        if mode == "shipped":
            found = D.detect(plane, conjugate, saturation=b.saturation, aperture=aperture)
        else:
            with predictions(*replaced(mode, ideal, plane, conjugate, aperture)):  # (the latent scene's test off)
                found = D.detect(plane, conjugate, saturation=b.saturation, aperture=aperture, latent=False)
            if mode == "latent, noisy":
                found = np.maximum(found, D.detect(plane, conjugate, saturation=b.saturation, aperture=aperture))
        pick(codes[..., None])[...] = found
    return codes


def row(preset, scene, exposure, seeds=(0, 1)):
    sensor = PRESETS[preset]
    for mode in ("shipped", "noise-free", "latent", "latent, noisy", "truth"):
        total, found, flagged = np.zeros(6), np.zeros(6), 0
        for seed in seeds:
            kw = dict(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene, exposure=exposure, seed=seed)
            b = simulate_burst(defects=0.005, **kw)
            hot = b.defects == D.HOT
            bins = np.clip(np.digitize(hot_offset_z(b, sensor, hot), EDGES) - 1, 0, len(EDGES) - 2)
            total += np.bincount(bins, minlength=6)
            found += np.bincount(bins, weights=(codes_of(b, sensor, mode)[hot] > 0).astype(float), minlength=6)
            flagged += int(np.count_nonzero(codes_of(simulate_burst(**kw), sensor, mode)))
        rates = " ".join(f"{f / t * 100:.0f}%({int(t)})" if t else "-" for f, t in zip(found, total))
        print(f"{preset:6s} {scene:12s} {exposure:5} {mode:13s}: {rates}; healthy flagged {flagged} of "
              f"{len(seeds) * 240 * 320}", flush=True)
    print(f"bins of hot_offset_z: {EDGES}", flush=True)


def zalias_row(preset, scene, exposure, seeds=(0, 1)):
    sensor = PRESETS[preset]
    aperture = 1.0 if sensor.cfa is None else 0.5
    total, found = {"z": np.zeros(6), "alias z": np.zeros(6)}, {"z": np.zeros(6), "alias z": np.zeros(6)}
    for seed in seeds:
        b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene, exposure=exposure, seed=seed,
                           defects=0.005)
        hot = b.defects == D.HOT
        latent = np.zeros(b.ideal.shape, np.float32)
        warp = GlobalWarp(b.homographies)
        for _, pick, S in plane_views(sensor.cfa, ("Y",)):
            ideal = np.ascontiguousarray(pick(b.ideal[..., None]), np.float32)
            pick(latent[..., None])[...] = left_out_rendering(ideal, warp.conjugate(S), 1e-3, aperture)
        flagged = (codes_of(b, sensor, "shipped")[hot] > 0).astype(float)
        aliased = hot_offset_z(b, sensor, hot, scene_error=latent.astype(np.float64) - b.ideal)
        for name, z in (("z", hot_offset_z(b, sensor, hot)), ("alias z", aliased)):
            bins = np.clip(np.digitize(z, EDGES) - 1, 0, len(EDGES) - 2)
            total[name] += np.bincount(bins, minlength=6)
            found[name] += np.bincount(bins, weights=flagged, minlength=6)
    for name in total:
        rates = " ".join(f"{f / t * 100:.0f}%({int(t)})" if t else "-" for f, t in zip(found[name], total[name]))
        print(f"{preset:6s} {scene:12s} {exposure:5} shipped, by {name:7s}: {rates}", flush=True)


@contextmanager
def light_captured(into):
    """The simulator's light before its mosaic, ``(H, W, 3)`` per frame, appended to ``into``."""
    shipped = sim._mosaic

    def mosaic(rgb, cfa):
        into.append(np.asarray(rgb, np.float32))
        return shipped(rgb, cfa)

    sim._mosaic = mosaic
    try:
        yield
    finally:
        sim._mosaic = shipped


def local_line(value, guide, radius=1):
    """``value`` fitted in each window of ``2 radius + 1`` photosites as a line of ``guide`` and
    evaluated at the window's centre (the ridge ``1e-4`` of the guide's 99th percentile squared);
    only the readings the rendering sees (``value > 0``) are fitted, and the others left as they are."""
    import cv2

    out = np.array(value)
    for t in range(len(value)):
        g, v = guide[t].astype(np.float64), value[t].astype(np.float64)
        seen = (v > 0).astype(np.float64)
        box = lambda a: cv2.boxFilter(a * seen, -1, (2 * radius + 1,) * 2, normalize=False,
                                      borderType=cv2.BORDER_REFLECT)
        n = np.maximum(box(1.0), 1.0)
        mg, mv = box(g) / n, box(v) / n
        slope = (box(g * v) / n - mg * mv) / (box(g * g) / n - mg * mg + 1e-4 * np.percentile(g, 99) ** 2)
        out[t] = np.where(v > 0, mv + slope * (g - mg), v)
    return out


@contextmanager
def latent_scene(mode, ideal, other):
    """The latent scene's test scoring against ``mode``'s scene (see the module)."""
    shipped = L._rendered

    def rendered(frames, read, warp, out, good, aperture, exposures, workers=1):
        x, usable = shipped(frames, ideal if mode == "noise-free" else read, warp, out, good, aperture, exposures,
                            workers)
        if mode == "cross-colour":
            x = local_line(x, other)
        return (ideal.copy() if mode == "the scene" else x), usable

    L._rendered = rendered
    try:
        yield
    finally:
        L._rendered = shipped


def latent_row(preset, scene, exposure, seeds=(0, 1)):
    sensor = PRESETS[preset]
    scale = exposure * sensor.full_well_e * sensor.dn_per_e  # light 1 in DN
    bursts = []
    for seed in seeds:
        light = []
        with light_captured(light):
            b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene, exposure=exposure,
                               seed=seed, defects=0.005)
        hot = b.defects == D.HOT
        bins = np.clip(np.digitize(hot_offset_z(b, sensor, hot), EDGES) - 1, 0, len(EDGES) - 2)
        bursts.append((b, scale * np.stack(light), hot, bins))
    for mode in ("shipped", "noise-free", "cross-colour", "the scene"):
        total, found = np.zeros(6), np.zeros(6)
        for b, light, hot, bins in bursts:
            frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
            warp = GlobalWarp(b.homographies)
            codes = np.zeros(hot.shape, np.uint8)
            for name, pick, S in plane_views(sensor.cfa, ("Y",)):
                ideal = np.ascontiguousarray(pick(b.ideal[..., None]), np.float32)
                others = light[..., [1]] if name[0] in "RB" else light[..., [0, 2]]
                other = np.ascontiguousarray(pick(others.sum(axis=-1, keepdims=True)), np.float32)
                with latent_scene(mode, ideal, other):
                    pick(codes[..., None])[...] = D.detect(pick(frames), warp.conjugate(S), saturation=b.saturation,
                                                           aperture=0.5)
            total += np.bincount(bins, minlength=6)
            found += np.bincount(bins, weights=(codes[hot] > 0).astype(float), minlength=6)
        rates = " ".join(f"{f / t * 100:.0f}%({int(t)})" if t else "-" for f, t in zip(found, total))
        print(f"{preset:6s} {scene:12s} {exposure:5} seeds {seeds} latent test against {mode:12s}: {rates}", flush=True)


if __name__ == "__main__" and len(sys.argv) == 5 and sys.argv[1] == "latent":
    for seeds in ((0, 1), (2, 3)):
        latent_row(sys.argv[2], sys.argv[3], float(sys.argv[4]), seeds)
elif __name__ == "__main__" and len(sys.argv) == 5 and sys.argv[1] == "zalias":
    for seeds in ((0, 1), (2, 3)):
        zalias_row(sys.argv[2], sys.argv[3], float(sys.argv[4]), seeds)
elif __name__ == "__main__" and len(sys.argv) == 4:
    row(sys.argv[1], sys.argv[2], float(sys.argv[3]))
elif __name__ == "__main__":
    for preset in ("raw12", "paper"):
        for scene in ("dead-leaves", "procedural"):
            for exposure in (0.75, 0.075):
                row(preset, scene, exposure)
