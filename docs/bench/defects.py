"""Detection rates of solve.defects.detect on simulated bursts, with their true motion.

    python docs/bench/defects.py

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

if __name__ == "__main__":
    for preset in ("paper", "raw12"):
        for scene in ("dead-leaves", "procedural"):
            for exposure, n in ((0.75, 8), (0.075, 8), (0.75, 5)):
                run(scene, preset, n, exposure)
