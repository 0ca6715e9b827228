"""Is the written confidence honest? (docs/limits.md, "Confidence")

    python docs/bench/confidence.py [SCENES [PRESETS [FRAMES [EXPOSURES]]]]   # default: moon,camera paper,raw12 9,16 0.5,0.075
    python docs/bench/confidence.py fit [PARTNERS]   # the accurate solver's own sigma_k by frame count
    python docs/bench/confidence.py spec [SEEDS]     # the bench's confidence group at other seeds (default 1,2,3)
    python docs/bench/confidence.py rggb640 [SEEDS]  # 640x480 12-bit RGGB dead leaves, 16 frames, per plane
    python docs/bench/confidence.py short [FRAMES]   # 12-bit RGGB bursts of 5 and 6 frames (40)
    python docs/bench/confidence.py structured       # sensors with column or row FPN (18)
    python docs/bench/confidence.py big [SCENE:SEED,...]  # 4000x3000x8 bursts (default dead-leaves:2,procedural:3,coffee:4)

Bursts of 240x320 rendered from scikit-image's sample photographs (not a dependency of gainfpn:
``pip install scikit-image``), 8-bit mono (``paper``) and 12-bit RGGB (``raw12``), at 50 % and
7.5 % exposure (scene value 1 at that share of the full well; a linearised photograph's mean is
0.07-0.27 of that, so 7.5 % puts the mean reading at 0.5-2 % of full scale), or at a mean level
(``m7.5``: the mean reading 7.5 % of full scale, issue 21's dark bursts), of 9 and 16 frames plus
one more that no fit sees. One JSON line per burst: per
decile of the written sigma_k, the RMS of the actual error of k over the RMS sigma_k (1 is
honest); the MSE before over after correction on the unseen frame; the residual gain FPN and
the reported input pixel FPN against the truth. About 15 minutes for the default.

``spec``: the bursts of ``gainfpn bench --group confidence`` (issue 21's: procedural and dead leaves,
8-bit and 12-bit RGGB, 75 % and 15 % exposure, bursts of 5 and 16 frames) at SEEDS instead of its 7,
one frame more each as above. About 5 minutes a seed.

``rggb640``: 640x480 12-bit RGGB dead-leaves bursts of 16 frames (default seeds 0,1,2), the
default config: the tenths over the whole map and over each colour plane (12 px inside). About 80 s
a seed.

``short``: 12-bit RGGB bursts of FRAMES (default 5,6), fitted on one fewer: procedural and dead leaves at
75 % and 15 % exposure, seeds 1-3, and ``camera``, ``moon``, ``chelsea`` and ``coffee`` at a mean of 7.5 % and
40 % of full scale, seed 7, each with one frame more as above. About 6 minutes.

``structured``: 240x320 bursts of sensors whose gain FPN is mostly per column or per row parity (8-bit
mono of 8 frames, 12-bit RGGB of 9; seeds 1 and 2), each with one frame more, as above (``error`` and
``sigma``: the RMS of k's actual error and of the written sigma_k). About 4 minutes.

``big``: 4000x3000x8 bursts of the paper's sensor (the bench's `balanced, 12 MP` point at other scenes
and seeds; SCENE a built-in scene or a scikit-image photograph), `balanced`: the tenths over the pixels
8 px inside. About 2 minutes a burst.

``fit``: dark procedural 240x320 bursts of the paper's sensor (7.5 % exposure, where k's error is
the noise's) of 3, 4, 5, 6, 8 and 12 frames, solved by the accurate solver with the true motion
and PARTNERS partner frames (default 8): k's actual error over the written sigma_k (RMS over the
pixels 16 px or more inside), and the same without the share of the residuals the fit took
(docs/method.md section 8, "sigma_k"), against the factor that share predicts. About 3 minutes.
"""

import json
import sys
import time

import numpy as np

from gainfpn_cli import api
from gainfpn_cli.metrics import confidence_deciles, interior_mask
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.result import sigma_from_confidence

MARGIN = 12  # px left out at the border, where trajectories leave the frame


def scene_of(name):
    """A built-in scene by name, or scikit-image's sample photograph, grey and linear (gamma 2.2)."""
    if name in ("procedural", "dead-leaves"):
        return name
    import skimage.data as d
    img = getattr(d, name)()
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    img = img.astype(np.float32) / (255.0 if img.max() > 1 else 1.0)
    return img ** 2.2


def case(scene, preset, exposure, frames, seed=7, sensor=None):
    """One burst's figures (see the module); ``exposure`` a number, or ``mL`` for a mean level of L %;
    ``sensor`` the preset's, or one given."""
    s = sensor or PRESETS[preset]
    image = scene_of(scene)
    if isinstance(exposure, str) and exposure.startswith("m"):
        exposure = round(float(exposure[1:]) / 100 / (float(np.mean(image)) if np.ndim(image) else 0.5), 4)
    b = simulate_burst(shape=(240, 320), n_frames=frames + 1, sensor=s, exposure=float(exposure), scene=image,
                       seed=seed)
    fr = b.frames.astype(np.float32) - s.black_level
    t = time.perf_counter()
    e = api.estimate(fr[:-1], cfa=s.cfa, saturation=s.white_level - s.black_level, **{"solver.workers": 2})
    dt = time.perf_counter() - t
    k, conf, a = e.k[..., 0], e.confidence[..., 0], b.gain
    use = np.zeros(a.shape, bool)
    use[MARGIN:-MARGIN, MARGIN:-MARGIN] = True
    unseen, ideal = fr[-1][use], b.ideal[-1][use]
    mse = float(np.mean((unseen - ideal) ** 2) / np.mean((k[use] * unseen - ideal) ** 2))
    use &= conf > 0
    p = k * a
    err = p / p[use].mean() - 1
    estimated = bool(use.any())  # none if every plane was rejected
    sigma = sigma_from_confidence(conf)
    deciles = [round(d, 2) for d in confidence_deciles(k, a, sigma, use)]
    level = round(100 * float(fr[:-1].mean()) / (s.white_level - s.black_level), 2)
    return dict(scene=scene, preset=preset, exposure=exposure, level=level, frames=frames, s=round(dt, 1),
                status=e.report.status,
                mse_unseen=round(mse, 3), residual=round(float(100 * np.std(err[use])), 3) if estimated else None,
                error=round(float(100 * np.sqrt(np.mean(err[use] ** 2))), 4) if estimated else None,
                sigma=round(float(100 * np.sqrt(np.mean(sigma[use] ** 2))), 4) if estimated else None,
                prnu_pixel=round(e.report.prnu_percent.pixel, 2),
                truth_pixel=round(100 * float(np.std(a / a.mean())), 2), deciles=deciles,
                models={name: plane.fpn_model for name, plane in e.report.planes.items()},
                solver=e.report.solver.method if e.report.solver else None)


def big(cases=(("dead-leaves", 2), ("procedural", 3), ("coffee", 4))):
    """One JSON line per (scene, seed): a 4000x3000x8 burst of the paper's sensor (supersampled 2x, as
    the bench's `balanced, 12 MP` point), `--preset balanced`, the tenths over the pixels 8 px inside."""
    for scene, seed in cases:
        b = simulate_burst(shape=(3000, 4000), n_frames=8, scene=scene_of(scene), seed=seed, supersample=2)
        fr = b.frames.astype(np.float32) - b.sensor.black_level
        t = time.perf_counter()
        e = api.estimate(fr, saturation=b.sensor.white_level - b.sensor.black_level, preset="balanced")
        dt = time.perf_counter() - t
        k, conf = e.k[..., 0], e.confidence[..., 0]
        use = (conf > 0) & interior_mask(k.shape, 8)
        deciles = [round(d, 2) for d in confidence_deciles(k, b.gain, sigma_from_confidence(conf), use)]
        print(json.dumps(dict(scene=scene, seed=seed, s=round(dt, 1), status=e.report.status, deciles=deciles)),
              flush=True)
        del b, fr, e


def fit(partners=8, seed=3):
    """One JSON line per frame count: the accurate solver's sigma_k against k's error (see the module)."""
    from gainfpn_cli.solve import accurate

    options = accurate.AccurateOptions(partners=partners, robust_rounds=1 if partners < 8 else 2)
    fractions = accurate._fit_fractions
    raw = lambda pairs, valid, shape: (np.ones(shape), np.ones(shape))  # noqa: E731 (nothing restored)
    for n in (3, 4, 5, 6, 8, 12):
        b = simulate_burst(shape=(240, 320), n_frames=n, exposure=0.075, seed=seed)
        fr = b.frames.astype(np.float32) - b.sensor.black_level
        row = dict(frames=n, partners=partners)
        for name, restored in (("ratio", True), ("ratio_raw", False)):
            accurate._fit_fractions = fractions if restored else raw
            try:
                r = accurate.solve_accurate(fr, b.homographies, options=options, saturation=b.saturation, workers=2)
            finally:
                accurate._fit_fractions = fractions
            use = (r.confidence > 0) & interior_mask(fr.shape[1:], 16)
            row[name] = round(confidence_deciles(r.k, b.gain, sigma_from_confidence(r.confidence), use, parts=1)[0], 3)
        m = 1.0 / (1 + min(partners, n - 1))
        row["predicted_raw"] = round(float(1.0 / np.sqrt((1 - m) * (1 - 1.0 / n - m))), 3)
        print(json.dumps(row), flush=True)


def spec(seeds=(1, 2, 3)):
    """One JSON line per burst of the bench's confidence group, at ``seeds`` (see the module)."""
    for seed in seeds:
        for scene in ("procedural", "dead-leaves"):
            for preset in ("paper", "raw12"):
                for exposure in (0.75, 0.15):
                    for frames in (5, 16):
                        print(json.dumps({**case(scene, preset, exposure, frames, seed), "seed": seed}), flush=True)


def short(counts=(5, 6)):
    """One JSON line per burst: RGGB bursts too short for halves (see the module)."""
    for frames in counts:
        for seed in (1, 2, 3):
            for scene in ("procedural", "dead-leaves"):
                for exposure in (0.75, 0.15):
                    print(json.dumps({**case(scene, "raw12", exposure, frames, seed), "seed": seed}), flush=True)
        for scene in ("camera", "moon", "chelsea", "coffee"):
            for exposure in ("m7.5", "m40"):
                print(json.dumps(case(scene, "raw12", exposure, frames)), flush=True)


#: ``structured``'s sensors: preset, pixel, column and row FPN, exposure, scene, frames.
STRUCTURED = [
    ("paper", 0.0, 0.02, 0.0, 0.75, "procedural", 8),
    ("paper", 0.0, 0.02, 0.0, 0.75, "dead-leaves", 8),
    ("paper", 0.003, 0.02, 0.0, 0.75, "procedural", 8),
    ("paper", 0.0, 0.0, 0.02, 0.75, "procedural", 8),
    ("paper", 0.002, 0.0, 0.0, 0.3, "procedural", 8),
    ("paper", 0.005, 0.0, 0.0, 0.075, "dead-leaves", 8),
    ("raw12", 0.002, 0.0, 0.0, 0.5, "procedural", 9),
    ("raw12", 0.0, 0.01, 0.0, 0.5, "procedural", 9),
    ("raw12", 0.003, 0.0, 0.0, 0.15, "dead-leaves", 9),
]


def structured():
    """One JSON line per burst of a sensor with structured FPN (see the module)."""
    import dataclasses

    for preset, pixel, column, row_, exposure, scene, frames in STRUCTURED:
        for seed in (1, 2):
            sensor = dataclasses.replace(PRESETS[preset], fpn_pixel=pixel, fpn_column=column, fpn_row=row_)
            row = case(scene, preset, exposure, frames, seed, sensor)
            print(json.dumps({**row, "pixel": pixel, "column": column, "row": row_, "seed": seed}), flush=True)


def rggb640(seeds=(0, 1, 2)):
    """One JSON line per seed: the tenths of a 640x480 RGGB burst's map, whole and per plane."""
    s = PRESETS["raw12"]
    for seed in seeds:
        b = simulate_burst(shape=(480, 640), n_frames=16, sensor=s, scene="dead-leaves", seed=seed)
        fr = b.frames.astype(np.float32) - s.black_level
        e = api.estimate(fr, cfa=s.cfa, saturation=s.white_level - s.black_level, **{"solver.workers": 2})
        k, conf, a = e.k[..., 0], e.confidence[..., 0], b.gain
        use = np.zeros(a.shape, bool)
        use[MARGIN:-MARGIN, MARGIN:-MARGIN] = True
        use &= conf > 0
        row = {"seed": seed}
        for name, (dy, dx) in (("all", (0, 0)), ("R", (0, 0)), ("G1", (0, 1)), ("G2", (1, 0)), ("B", (1, 1))):
            step = 1 if name == "all" else 2
            at = (slice(dy, None, step), slice(dx, None, step))
            row[name] = [round(d, 2) for d in confidence_deciles(k[at], a[at], sigma_from_confidence(conf[at]),
                                                                 use[at])]
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "rggb640":
        rggb640([int(s) for s in sys.argv[2].split(",")] if len(sys.argv) > 2 else (0, 1, 2))
        sys.exit()
    if len(sys.argv) > 1 and sys.argv[1] == "short":
        short([int(f) for f in sys.argv[2].split(",")] if len(sys.argv) > 2 else (5, 6))
        sys.exit()
    if len(sys.argv) > 1 and sys.argv[1] == "structured":
        structured()
        sys.exit()
    if len(sys.argv) > 1 and sys.argv[1] == "big":
        big([(c.split(":")[0], int(c.split(":")[1])) for c in sys.argv[2].split(",")] if len(sys.argv) > 2
            else (("dead-leaves", 2), ("procedural", 3), ("coffee", 4)))
        sys.exit()
    if len(sys.argv) > 1 and sys.argv[1] == "fit":
        fit(int(sys.argv[2]) if len(sys.argv) > 2 else 8)
        sys.exit()
    if len(sys.argv) > 1 and sys.argv[1] == "spec":
        spec([int(s) for s in sys.argv[2].split(",")] if len(sys.argv) > 2 else (1, 2, 3))
        sys.exit()
    scenes = sys.argv[1].split(",") if len(sys.argv) > 1 else ("moon", "camera")
    counts = [int(f) for f in sys.argv[3].split(",")] if len(sys.argv) > 3 else (9, 16)
    for scene in scenes:
        for preset in (sys.argv[2].split(",") if len(sys.argv) > 2 else ("paper", "raw12")):
            for exposure in (sys.argv[4].split(",") if len(sys.argv) > 4 else (0.5, 0.075)):
                exposure = exposure if str(exposure).startswith("m") else float(exposure)
                for frames in counts:
                    print(json.dumps(case(scene, preset, exposure, frames)), flush=True)
