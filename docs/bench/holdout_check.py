"""Measure the hold-out check (docs/method.md section 12, docs/limits.md).

    python docs/bench/holdout_check.py bias    # the check against two frames no fit saw
    python docs/bench/holdout_check.py rates   # false accepts and rejects on 48 simulated bursts
    python docs/bench/holdout_check.py short   # the same on short and very small bursts (42)
    python docs/bench/holdout_check.py rggb    # RGGB bursts of 5 fitted frames, too few for halves (12):
                                               # written k = 1 (checking.short_mosaic); their unguarded maps

Every burst is simulated with one frame more than the estimate gets: that unseen frame's MSE
before over after correction says whether a map helps (frame 0 was fitted, and its MSE
flatters k); a burst the estimate refuses writes no map. Prints one JSON line per burst, then
the counts. Takes about 17 minutes (rates), 6 (short) and 2 (rggb).
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np

from gainfpn_cli import api, solving
from gainfpn_cli.errors import EstimationError
from gainfpn_cli.geometry.planes import solve_grids
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.holdout import holdout_checks

MONO12 = dataclasses.replace(PRESETS["raw12"], cfa=None)
MARGIN = 12  # px left out at the border, where trajectories leave the frame


def bias():
    for scene, exposure in (("dead-leaves", 0.05), ("dead-leaves", 0.1), ("procedural", 0.05)):
        sensor = dataclasses.replace(MONO12, fpn_pixel=0.02)
        b = simulate_burst(shape=(240, 320), n_frames=9, sensor=sensor, exposure=exposure, scene=scene, seed=3)
        frames = b.frames.astype(np.float32) - sensor.black_level
        est = api.estimate(frames[:8], saturation=sensor.white_level - sensor.black_level)
        grids = list(solve_grids(None, ("Y",), frames.shape[1:], greens_together=True))

        def ratio(pair):
            return holdout_checks(frames[list(pair), ..., None], None, np.ones(2), GlobalWarp(b.homographies[list(pair)]),
                                  est.k, grids=grids, saturation=None)["Y"].ratio

        print(json.dumps({"scene": scene, "exposure": exposure, "check": est.report.holdout.residual_ratio,
                          "unfitted_pair": ratio((8, 7)), "reference_under_written_k": ratio((0, 7))}), flush=True)


def pool():
    """48 bursts: 36 that are dark, aliased, short or forced to a wrong motion model, 12 good."""
    for seed in range(6):
        scene = ("procedural", "dead-leaves")[seed % 2]
        yield dict(kind="dark 12-bit", sensor=dataclasses.replace(MONO12, fpn_pixel=0.02),
                   exposure=(0.02, 0.04, 0.08)[seed % 3], frames=8, scene=scene, seed=seed)
        yield dict(kind="dark 12-bit, 5 frames", sensor=dataclasses.replace(MONO12, fpn_pixel=0.01), exposure=0.05,
                   frames=5, scene=scene, seed=seed)
        yield dict(kind="dark RGGB", sensor=PRESETS["raw12"], exposure=(0.03, 0.06)[seed % 2], frames=6, scene=scene,
                   seed=seed)
        yield dict(kind="aliased RGGB", sensor=dataclasses.replace(PRESETS["raw12"], fpn_pixel=0.005), exposure=0.75,
                   frames=6, scene="dead-leaves", seed=seed)
        yield dict(kind="4 frames", sensor=dataclasses.replace(PRESETS["paper"], fpn_pixel=0.01), exposure=0.3,
                   frames=4, scene=scene, seed=seed)
        yield dict(kind="forced translation", sensor=dataclasses.replace(MONO12, fpn_pixel=0.01), exposure=0.5,
                   frames=8, scene=scene, seed=seed, shake=Shake(rotation_deg=1.0),
                   overrides={"motion.model": "translation"})
        yield dict(kind="good 8-bit", sensor=PRESETS["paper"], exposure=0.75, frames=8, scene=scene, seed=seed)
        yield dict(kind="good RGGB", sensor=PRESETS["raw12"], exposure=0.5, frames=8, scene="procedural", seed=seed)


def short_bursts():
    """42 bursts: good 8-bit bursts of 5, 6 and 8 frames at 96x128 and 240x320, and very small
    aliased ones (64x80, 5 frames, the scene point-sampled), 6 seeds each."""
    for seed in range(6):
        scene = ("procedural", "dead-leaves")[seed % 2]
        for shape in ((96, 128), (240, 320)):
            for frames in (5, 6, 8):
                yield dict(kind=f"good {shape[0]}x{shape[1]}, {frames} frames", sensor=PRESETS["paper"],
                           exposure=0.75, frames=frames, scene=scene, seed=seed, shape=shape)
        yield dict(kind="64x80 point-sampled, 5 frames", sensor=PRESETS["paper"], exposure=0.75, frames=5,
                   scene=scene, seed=seed, shape=(64, 80), supersample=1)


def rggb_bursts():
    """12 RGGB bursts of 6 frames (5 fitted: too few for halves, and a mosaic's sigma_k is not measured on
    the scene model's rendering), 1 % pixel FPN at 50 % exposure, procedural and dead leaves, 6 seeds each."""
    for seed in range(6):
        for scene in ("procedural", "dead-leaves"):
            yield dict(kind=f"RGGB 6 frames, {scene}", sensor=PRESETS["raw12"], exposure=0.5, frames=6, scene=scene,
                       seed=seed)


def rates(cases=pool):
    unguarded = {}
    solve_planes = solving.solve_planes

    def keep(*args, **kwargs):  # the map before the check
        out = solve_planes(*args, **kwargs)
        if kwargs.get("regions") is None:
            unguarded["k"] = out.k.copy()
        return out

    solving.solve_planes = keep
    rows = []
    for case in cases():
        s = case["sensor"]
        b = simulate_burst(shape=case.get("shape", (240, 320)), n_frames=case["frames"] + 1, sensor=s,
                           exposure=case["exposure"], scene=case["scene"], seed=100 + case["seed"],
                           shake=case.get("shake", Shake()), supersample=case.get("supersample", 4))
        frames = b.frames.astype(np.float32) - s.black_level
        try:
            est = api.estimate(frames[:-1], cfa=s.cfa, saturation=s.white_level - s.black_level,
                               **case.get("overrides", {}))
        except EstimationError as exc:  # refused: no map written
            rows.append({"kind": case["kind"], "seed": case["seed"], "status": "refused", "error": str(exc)})
            print(json.dumps(rows[-1]), flush=True)
            continue
        inner = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
        unseen, ideal = frames[-1][inner], b.ideal[-1][inner]

        def mse_ratio(k):
            return float(np.mean((unseen - ideal) ** 2) / np.mean((k[..., 0][inner] * unseen - ideal) ** 2))

        row = {"kind": case["kind"], "seed": case["seed"], "unguarded": mse_ratio(unguarded["k"]),
               "written": mse_ratio(est.k), "status": est.report.status,
               "ratio": est.report.holdout.residual_ratio, "standard_error": est.report.holdout.standard_error,
               "left_out_blocks": sum(p.left_out_blocks for p in est.report.holdout.planes.values())}
        rows.append(row)
        print(json.dumps(row), flush=True)
    refused = [r for r in rows if r["status"] == "refused"]
    rows = [r for r in rows if r["status"] != "refused"]
    harmful = [r for r in rows if r["unguarded"] < 1.0]
    helpful = [r for r in rows if r["unguarded"] >= 1.0]
    print(json.dumps({"refused": len(refused),
        "harmful": len(harmful), "accepted_harmful": sum(r["status"] != "rejected" for r in harmful),
        "helpful": len(helpful), "rejected_helpful": sum(r["status"] == "rejected" for r in helpful),
        "written_worse_than_none": sum(r["written"] < 1.0 for r in rows)}))


if __name__ == "__main__":
    {"bias": bias, "rates": rates, "short": lambda: rates(short_bursts),
     "rggb": lambda: rates(rggb_bursts)}[sys.argv[1] if len(sys.argv) > 1 else "rates"]()
