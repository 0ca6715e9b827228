"""Detection rates of solve.defects.detect on simulated bursts, with their true motion.

    python docs/bench/defects.py        # the table of docs/limits.md
    python docs/bench/defects.py hot    # hot photosites found, by offset over (level x pixel FPN)
    python docs/bench/defects.py hotz   # ... by how well the offset could be told from a gain
    python docs/bench/defects.py deadz  # dead and stuck ones found, by how plainly they differ from a healthy one

Per sensor preset, scene, exposure and frame count: the percentage of each simulated kind
flagged (in parentheses: flagged as that kind), over two 240x320 bursts with 0.5 % defects; and
the healthy photosites flagged on the same two bursts without defects (per 10^4, by kind: hot,
dead, stuck). About 30 s.
"""
import sys
import time

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2]))
from gainfpn_cli.geometry.planes import plane_views
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import hot_offset_z, response_z
from gainfpn_cli.solve import defects as D


def codes_of(b, sensor):
    frames = (b.frames.astype(np.float32) - sensor.black_level)[..., None]
    warp = GlobalWarp(b.homographies)
    codes = np.zeros(frames.shape[1:3], np.uint8)
    for name, pick, S in plane_views(sensor.cfa, ("Y",)):
        pick(codes[..., None])[...] = D.detect(pick(frames), warp.conjugate(S), saturation=b.saturation)
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


if __name__ == "__main__" and sys.argv[1:] == ["hot"]:
    hot_found(offset_over_gain_spread, (0, 2, 4, 6, 8, 10, 15, np.inf))
elif __name__ == "__main__" and sys.argv[1:] == ["hotz"]:
    hot_found(hot_offset_z, (0, 4, 6, 10, 20, 40, np.inf))
elif __name__ == "__main__" and sys.argv[1:] == ["deadz"]:
    hot_found(response_z, (0, 6, 10, 20, 40, np.inf), ("dead", "stuck"))
elif __name__ == "__main__":
    for preset in ("paper", "raw12"):
        for scene in ("dead-leaves", "procedural"):
            for exposure, n in ((0.75, 8), (0.075, 8), (0.75, 5)):
                run(scene, preset, n, exposure)
