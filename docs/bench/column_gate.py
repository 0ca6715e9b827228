"""Does the column-model gate tell a sensor's column FPN from a scene's vertical edges?
(docs/method.md section 11, "FPN model")

    python docs/bench/column_gate.py [sensor|photos [SCENES]]   # default: both; photos of camera,moon

``sensor``: 240x320 8-bit bursts of 8 frames (the paper's sensor with 3 % pixel FPN) and column FPN
of 0 to 4 %, dead leaves and procedural scenes, solved by the accurate solver with the true
motion: the column agreement (standard errors), the FPN model chosen with the gate and by AIC
alone, and the residual gain FPN of each (percent, 8 px inside). About 3 minutes.

``photos``: 9-frame 12-bit RGGB bursts (50 % exposure, no column FPN) rendered from scikit-image's
sample photographs, estimated end to end twice, with the gate and by AIC alone: per plane the
agreement, the model and the residual gain FPN of the written map against the truth's own spread.
About 1 minute per scene.
"""

import json
import sys

import numpy as np
from confidence import scene_of

from gainfpn_cli import api, metrics
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve import fpnmodel
from gainfpn_cli.solve.accurate import solve_accurate

MARGIN = 8  # px left out at the border, where trajectories leave the frame
PLANES = {"R@00": (0, 0), "G@01": (0, 1), "G@10": (1, 0), "B@11": (1, 1)}  # report.json names


SHIPPED = fpnmodel.COLUMN_Z


def gated(gate: bool):
    """The gate on (the shipped COLUMN_Z) or off (AIC alone)."""
    fpnmodel.COLUMN_Z = SHIPPED if gate else -np.inf


def sensor_case(scene, column, seed=1):
    b = simulate_burst(shape=(240, 320), n_frames=8, seed=seed, scene=scene,
                       sensor=with_overrides(PRESETS["paper"], fpn_pixel=0.03, fpn_column=column))
    r = solve_accurate(b.frames.astype(np.float32), b.homographies, saturation=b.saturation, workers=2)
    mask = (r.confidence > 0) & metrics.interior_mask(r.k.shape, MARGIN)
    row = dict(scene=scene, column_fpn=column)
    for gate in (True, False):
        gated(gate)
        m = fpnmodel.select_model(r.k, r.confidence)
        row["gate" if gate else "aic"] = dict(model=m.chosen,
                                              residual=round(metrics.residual_fpn_percent(m.k, b.gain, mask), 3))
        row["agreement"] = round(m.column_agreement, 1)
    gated(True)
    return row


def photo_case(scene, seed=7):
    s = PRESETS["raw12"]
    b = simulate_burst(shape=(240, 320), n_frames=9, sensor=s, exposure=0.5, scene=scene_of(scene), seed=seed)
    fr = b.frames.astype(np.float32) - s.black_level
    row = dict(scene=scene, truth={n: round(100 * float(np.std(b.gain[dy::2, dx::2][MARGIN:-MARGIN, MARGIN:-MARGIN])), 3)
                                   for n, (dy, dx) in PLANES.items()})
    for gate in (True, False):
        gated(gate)
        e = api.estimate(fr, cfa=s.cfa, saturation=s.white_level - s.black_level, **{"solver.workers": 2})
        k, conf = e.k[..., 0], e.confidence[..., 0]
        planes = {}
        for n, (dy, dx) in PLANES.items():
            p = (k * b.gain)[dy::2, dx::2][MARGIN:-MARGIN, MARGIN:-MARGIN]
            seen = conf[dy::2, dx::2][MARGIN:-MARGIN, MARGIN:-MARGIN] > 0
            plane = e.report.planes.get(n)
            planes[n] = dict(model=plane.fpn_model if plane else None,
                             agreement=plane.column_agreement if plane else None,
                             residual=round(100 * float(np.std(p[seen] / p[seen].mean())), 3) if seen.any() else None)
        row["gate" if gate else "aic"] = dict(status=e.report.status, planes=planes)
    gated(True)
    return row


if __name__ == "__main__":
    parts = [sys.argv[1]] if len(sys.argv) > 1 else ["sensor", "photos"]
    if "sensor" in parts:
        for scene in ("dead-leaves", "procedural"):
            for column in (0.0, 0.002, 0.005, 0.01, 0.04):
                print(json.dumps(sensor_case(scene, column)), flush=True)
    if "photos" in parts:
        for scene in (sys.argv[2].split(",") if len(sys.argv) > 2 else ("camera", "moon")):
            print(json.dumps(photo_case(scene)), flush=True)
