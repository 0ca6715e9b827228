"""Detection rates of solve.defects.detect on simulated bursts, with their true motion.

    python docs/bench/defects.py        # the table of docs/limits.md
    python docs/bench/defects.py hot    # hot photosites found, by offset over (level x pixel FPN)
    python docs/bench/defects.py hotz   # ... by how well the offset could be told from a gain
    python docs/bench/defects.py deadz  # dead and stuck ones found, by how plainly they differ from a healthy one
    python docs/bench/defects.py predict  # the error of the two predictions of the scene (solve.predict)
    python docs/bench/defects.py photos   # healthy photosites flagged on photographs (scikit-image's)
    python docs/bench/defects.py clean    # ... on ten defect-free 144x176 bursts per row, 5-8 frames
    python docs/bench/defects.py model    # hot ones found by the scene model's offset test, by hotz's bins
    python docs/bench/defects.py model photos  # healthy photosites that test flags on photographs
    python docs/bench/defects.py model scores  # the healthy photosites' scores of that test
    python docs/bench/defects.py threads  # the search's time on 1 and 2 threads, 2000x1500x8 (same codes)
    python docs/bench/defects.py holdout  # the hold-out on raw12 bursts with and without 1 % defects

Per sensor preset, scene, exposure and frame count: the percentage of each simulated kind
flagged (in parentheses: flagged as that kind), over two 240x320 bursts with 0.5 % defects; and
the healthy photosites flagged on the same two bursts without defects (per 10^4, by kind: hot,
dead, stuck). About 30 s.
"""
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2]))
from gainfpn_cli.geometry.planes import plane_views
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import hot_offset_z, response_z
from gainfpn_cli.solve import defects as D
from gainfpn_cli.solve import predict as P


def codes_of(b, sensor):
    frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
    warp = GlobalWarp(b.homographies)
    codes = np.zeros(frames.shape[1:3], np.uint8)
    for name, pick, S in plane_views(sensor.cfa, ("Y",)):
        pick(codes[..., None])[...] = D.detect(pick(frames), warp.conjugate(S), saturation=b.saturation,
                                               aperture=0.5 if sensor.cfa else 1.0)
    return codes

def run(scene="dead-leaves", preset="paper", n=8, exposure=0.75, frac=0.005, seeds=(0, 1), shape=(240, 320), **kw):
    sensor = PRESETS[preset]
    found = {k: [0, 0, 0] for k in D.KINDS}
    fp, total = np.zeros(5, int), 0
    t0 = time.perf_counter()
    for seed in seeds:
        b = simulate_burst(shape=shape, n_frames=n, sensor=sensor, scene=scene, exposure=exposure, defects=frac, seed=seed, **kw)
        codes = codes_of(b, sensor)
        for kind, code in D.KINDS.items():
            m = b.defects == code
            found[kind][0] += m.sum(); found[kind][1] += (codes[m] > 0).sum(); found[kind][2] += (codes[m] == code).sum()
        clean = simulate_burst(shape=shape, n_frames=n, sensor=sensor, scene=scene, exposure=exposure, seed=seed, **kw)
        codes = codes_of(clean, sensor)
        fp += np.bincount(codes.ravel(), minlength=5); total += codes.size
    out = {k: f"{v[1]/v[0]*100:.1f}%({v[2]/v[0]*100:.0f})" for k, v in found.items() if v[0]}
    out["fp"] = f"{(total - fp[0]) / total * 1e4:.2f}e-4 {fp[1:]}"
    print(f"{scene:12s} {preset:6s} n={n} exp={exposure}", out, f"{time.perf_counter() - t0:.1f}s", flush=True)

def offset_over_gain_spread(b, sensor, hot):
    """Each ``hot`` photosite's offset over (its mean level x the pixel FPN): an offset ``b`` at
    level ``x`` reads as a gain ``1 + b / x``, seen only beyond the gain spread."""
    level = b.gain[None] * b.ideal
    offset = np.mean(b.frames.astype(np.float64) - sensor.black_level - level, axis=0)
    return offset[hot] / (level.mean(axis=0)[hot] * sensor.fpn_pixel)


def hot_found(measure, edges, kinds=("hot",)):
    """Per sensor, scene and exposure (8 frames, two 240x320 bursts, 0.5 % defects): the share of
    the photosites of ``kinds`` flagged, binned by ``measure(burst, sensor, where)``."""
    edges = np.asarray(edges, float)
    for preset in ("raw12", "paper"):
        sensor = PRESETS[preset]
        for scene in ("dead-leaves", "procedural"):
            for exposure in (0.75, 0.075):
                found, total = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
                for seed in (0, 1):
                    b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene, exposure=exposure,
                                       defects=0.005, seed=seed)
                    hot = np.isin(b.defects, [D.KINDS[k] for k in kinds])
                    bins = np.clip(np.digitize(measure(b, sensor, hot), edges) - 1, 0, len(edges) - 2)
                    total += np.bincount(bins, minlength=len(edges) - 1)
                    found += np.bincount(bins, weights=(codes_of(b, sensor)[hot] > 0).astype(float),
                                         minlength=len(edges) - 1)
                rates = " ".join(f"{f / t * 100:.0f}%({int(t)})" if t else "-" for f, t in zip(found, total))
                print(f"{preset:6s} {scene:12s} {exposure:5}: {rates}", flush=True)
    print(f"bins of {measure.__name__}:", edges)


def model_scores(b, sensor, codes):
    """The scene solver's offset scores of a monochrome burst's photosites the search left healthy
    (true motion, the search's defects repaired first, as the pipeline does; every frame fitted; 0
    at the search's defects)."""
    from gainfpn_cli.defective import repair
    from gainfpn_cli.solve.scene import solve_scene

    frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
    frames = np.stack([repair(f, codes[..., None], None, ("Y",)) for f in frames])[..., 0]
    result = solve_scene(frames, GlobalWarp(b.homographies), saturation=b.saturation)
    return np.where(codes == 0, result.offsets, 0)


def model_flags(b, sensor, codes):
    """The photosites the scene solver's offset test flags besides the search's (:func:`model_scores`)."""
    from gainfpn_cli.defective import offset_shown

    return offset_shown(model_scores(b, sensor, codes))


def healthy_scores(seeds=(40, 41)):
    """The offset scores of healthy photosites (defect-free 240x320 paper bursts of 8 frames, both
    scenes and the photographs, 75 % and 7.5 %): their spread per burst, the largest, and how many
    pass the threshold."""
    from confidence import scene_of
    from gainfpn_cli.defective import Z_MODEL_OFFSET

    sensor = PRESETS["paper"]
    spreads, largest, passed, scored = [], {}, 0, 0
    for name in ("dead-leaves", "procedural") + PHOTOS:
        for exposure in (0.75, 0.075):
            for seed in seeds:
                b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene_of(name),
                                   exposure=exposure, seed=seed)
                z = model_scores(b, sensor, codes_of(b, sensor))
                z = z[z != 0]
                spreads.append(float(np.std(z)))
                largest[name] = max(largest.get(name, -np.inf), float(z.max()))
                passed += int(np.count_nonzero(z > Z_MODEL_OFFSET))
                scored += z.size
    print(f"{len(spreads)} bursts: spread {min(spreads):.2f}-{max(spreads):.2f}; largest by scene "
          f"{ {k: round(v, 2) for k, v in largest.items()} }; above {Z_MODEL_OFFSET}: {passed} of {scored}")


def model_found(scenes=("dead-leaves", "procedural"), exposures=(0.75, 0.075), seeds=(0, 1)):
    """Per scene and exposure (paper 8-bit, 8 frames, 240x320, 0.5 % defects): the share of the hot
    photosites flagged by the search alone and with the scene model's offset test, binned as
    ``hotz``; and the healthy photosites the test flags on the same bursts without defects."""
    edges = np.array([0, 4, 6, 10, 20, 40, np.inf])
    sensor = PRESETS["paper"]
    for scene in scenes:
        for exposure in exposures:
            total, before, after, false, pixels = np.zeros(6), np.zeros(6), np.zeros(6), 0, 0
            for seed in seeds:
                kw = dict(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene, exposure=exposure, seed=seed)
                b = simulate_burst(defects=0.005, **kw)
                codes = codes_of(b, sensor)
                hot = b.defects == D.HOT
                bins = np.clip(np.digitize(hot_offset_z(b, sensor, hot), edges) - 1, 0, 5)
                total += np.bincount(bins, minlength=6)
                before += np.bincount(bins, weights=(codes[hot] > 0).astype(float), minlength=6)
                found = (codes > 0) | model_flags(b, sensor, codes)
                after += np.bincount(bins, weights=found[hot].astype(float), minlength=6)
                clean = simulate_burst(**kw)
                false += int(model_flags(clean, sensor, codes_of(clean, sensor)).sum())
                pixels += clean.frames[0].size

            def rates(found):
                return " ".join(f"{f / t * 100:.0f}%({int(t)})" if t else "-" for f, t in zip(found, total))

            print(f"{scene:12s} {exposure:5}: search {rates(before)}; with the model {rates(after)}; "
                  f"healthy flagged by the model {false} ({false / pixels * 1e4:.2f}e-4)", flush=True)
    print("bins of hot_offset_z:", edges)


def model_photographs(scenes=None, seeds=(40, 41)):
    """Healthy photosites the scene model's offset test flags on defect-free 240x320 paper bursts of 8
    frames rendered from photographs, per exposure."""
    from confidence import scene_of

    sensor = PRESETS["paper"]
    for exposure in (0.75, 0.075):
        flagged = {}
        for name in scenes or PHOTOS:
            flagged[name] = 0
            for seed in seeds:
                b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene_of(name), exposure=exposure,
                                   seed=seed)
                flagged[name] += int(model_flags(b, sensor, codes_of(b, sensor)).sum())
        print(f"paper {exposure:5}: {flagged}; in all {sum(flagged.values())} of "
              f"{len(flagged) * len(seeds) * 240 * 320}", flush=True)


def prediction_errors(preset="raw12", scene="dead-leaves", n=8, seed=0):
    """The relative error of each prediction of :mod:`solve.predict` against the noise-free frames
    (noise off, the gains 1: what is left is the prediction's own), per plane: the mean absolute
    and the 90th percentile, over the photosites both predict from the frames above 5 % of the
    plane's peak."""
    sensor = replace(PRESETS[preset], shot_noise=False, read_noise_e=0.0, fpn_pixel=0.0)
    b = simulate_burst(shape=(240, 320), n_frames=n, sensor=sensor, scene=scene, exposure=0.75, seed=seed)
    warp = GlobalWarp(b.homographies)
    for name, pick, S in plane_views(sensor.cfa, ("Y",)):
        ideal = np.ascontiguousarray(pick(b.ideal[..., None]), np.float32)

        def everywhere(t, frame):
            return np.ones(frame.shape, bool)

        median, valid, from_frames = P.scene_along(ideal, everywhere, warp.conjugate(S))
        sharp, known = P.nearest_along(ideal, everywhere, warp.conjugate(S))
        both = valid & from_frames & known & (ideal > 0.05 * ideal.max())
        line = []
        for label, x in (("median", median), ("sharper", sharp)):
            error = np.abs(x[both] / ideal[both] - 1)
            line.append(f"{label} {np.mean(error) * 100:.2f} % / {np.quantile(error, 0.9) * 100:.1f} %")
        print(f"{preset} {scene} {name}: " + ", ".join(line), flush=True)


PHOTOS = ("camera", "moon", "text", "gravel", "chelsea", "grass", "brick", "coins", "astronaut", "cell")


def photographs(scenes=PHOTOS, seeds=(40, 41)):
    """Healthy photosites flagged on defect-free 240x320 bursts of 8 frames rendered from photographs
    (grey, linear: docs/bench/confidence.py's), per sensor and exposure, by scene and in all."""
    from confidence import scene_of

    for preset in ("raw12", "paper"):
        sensor = PRESETS[preset]
        for exposure in (0.75, 0.075):
            flagged, kinds = {}, np.zeros(4, int)
            for name in scenes:
                flagged[name] = 0
                for seed in seeds:
                    b = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene=scene_of(name),
                                       exposure=exposure, seed=seed)
                    codes = codes_of(b, sensor)
                    flagged[name] += int(np.count_nonzero(codes))
                    kinds += np.bincount(codes.ravel(), minlength=4)
            per = 1e4 / (len(seeds) * 240 * 320)
            worst = max(flagged, key=flagged.get)
            print(f"{preset:6s} {exposure:5}: {flagged}; worst {worst} {flagged[worst] * per:.2f}e-4, "
                  f"hot / dead / stuck {kinds[1:]}", flush=True)


def clean(frames=(5, 6, 7, 8), seeds=range(20, 30)):
    """Healthy photosites flagged on ten defect-free 144x176 bursts per sensor, scene and exposure
    (true motion), at each frame count (docs/limits.md's table of them; about 20 minutes)."""
    for preset in ("raw12", "paper"):
        sensor = PRESETS[preset]
        for exposure in (0.75, 0.075):
            for scene in ("dead-leaves", "procedural"):
                counts = []
                for n in frames:
                    bursts = (simulate_burst(shape=(144, 176), n_frames=n, sensor=sensor, scene=scene,
                                             exposure=exposure, seed=seed) for seed in seeds)
                    counts.append(sum(int(np.count_nonzero(codes_of(b, sensor))) for b in bursts))
                print(f"{preset:6s} {scene:12s} {exposure:5}: flagged at {frames} frames {counts} of "
                      f"{len(seeds) * 144 * 176}", flush=True)


def threads(shape=(1500, 2000), n=8, rounds=2):
    """Seconds of the search (every plane, true motion, 0.2 % defects, frames of different exposures)
    on 1 and 2 threads, alternating, and whether the codes and noise models are the same."""
    for preset in ("paper", "raw12"):
        sensor = PRESETS[preset]
        b = simulate_burst(shape=shape, n_frames=n, sensor=sensor, scene="dead-leaves", defects=0.002, seed=1,
                           exposure_jitter=0.02)
        frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
        warp = GlobalWarp(b.homographies)
        D.survey(frames[:, :64, :64, 0], warp)  # compiled before the clock starts
        seen = {}
        for threads in (1, 2) * rounds:
            t0 = time.perf_counter()
            found = [D.survey(pick(frames), warp.conjugate(S), saturation=b.saturation, exposures=b.exposures,
                              aperture=0.5 if sensor.cfa else 1.0, threads=threads) for _, pick, S in plane_views(sensor.cfa, ("Y",))]
            seconds = time.perf_counter() - t0
            result = [(f.codes.tobytes(), f.noise) for f in found]
            same = seen.setdefault("result", result) == result
            print(f"{preset:6s} {threads} thread(s): {seconds:.2f} s, the same as on one: {same}", flush=True)


def holdout(shapes=((160, 192), (192, 256)), seeds=(4, 5)):
    """Does the hold-out check accept a burst for what k does to its hot photosites? ``api.estimate``
    (motion estimated, defaults) of raw12 RGGB dead-leaves bursts of 7 frames at 30 %, each without and
    with 1 % defects: the check's verdict and residual ratio, the share of k = 1, and the healthy
    photosites' residual gain FPN against doing nothing."""
    from gainfpn_cli import api
    from gainfpn_cli.metrics import residual_fpn_percent

    sensor = PRESETS["raw12"]
    for shape in shapes:
        for seed in seeds:
            for frac in (0.0, 0.01):
                b = simulate_burst(shape=shape, n_frames=7, sensor=sensor, scene="dead-leaves", exposure=0.3,
                                   seed=seed, defects=frac)
                r = api.estimate(b.frames.astype(np.float32) - sensor.black_level, cfa=sensor.cfa,
                                 saturation=sensor.white_level - sensor.black_level)
                healthy = np.ones(shape, bool) if b.defects is None else b.defects == D.HEALTHY
                k = r.k[..., 0]
                check = r.report.holdout
                print(f"{shape[1]}x{shape[0]} seed {seed} defects {frac}: hold-out "
                      f"{'accepted' if check.passed else 'rejected'} ({check.residual_ratio:.4f}), k = 1 on "
                      f"{np.mean(k == 1) * 100:.0f} %, healthy residual {residual_fpn_percent(k, b.gain, healthy):.3f} % "
                      f"against {residual_fpn_percent(np.ones_like(k), b.gain, healthy):.3f} %", flush=True)


if __name__ == "__main__" and sys.argv[1:] == ["threads"]:
    threads()
elif __name__ == "__main__" and sys.argv[1:] == ["holdout"]:
    holdout()
elif __name__ == "__main__" and sys.argv[1:] == ["photos"]:
    photographs()
elif __name__ == "__main__" and sys.argv[1:] == ["clean"]:
    clean()
elif __name__ == "__main__" and sys.argv[1:] == ["predict"]:
    for preset in ("raw12", "paper"):
        for scene in ("dead-leaves", "procedural"):
            prediction_errors(preset, scene)
elif __name__ == "__main__" and sys.argv[1:] == ["hot"]:
    hot_found(offset_over_gain_spread, (0, 2, 4, 6, 8, 10, 15, np.inf))
elif __name__ == "__main__" and sys.argv[1:] == ["model"]:
    model_found()
elif __name__ == "__main__" and sys.argv[1:] == ["model", "photos"]:
    model_photographs()
elif __name__ == "__main__" and sys.argv[1:] == ["model", "scores"]:
    healthy_scores()
elif __name__ == "__main__" and sys.argv[1:] == ["hotz"]:
    hot_found(hot_offset_z, (0, 4, 6, 10, 20, 40, np.inf))
elif __name__ == "__main__" and sys.argv[1:] == ["deadz"]:
    hot_found(response_z, (0, 6, 10, 20, 40, np.inf), ("dead", "stuck"))
elif __name__ == "__main__":
    for preset in ("paper", "raw12"):
        for scene in ("dead-leaves", "procedural"):
            for exposure, n in ((0.75, 8), (0.075, 8), (0.75, 5)):
                run(scene, preset, n, exposure)
