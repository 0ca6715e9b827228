"""What the scene solver's time goes to at 12 MP (docs/limits.md, "The scene solver")

    python docs/bench/scene_cost.py BURST [OUT]   # OUT: where the three estimates go (default: BURST.cost)
    python docs/bench/scene_cost.py tiles BURST   # its tiles' parts, on one worker

BURST is a simulated burst (``gainfpn simulate big --size 4000x3000 --scene dead-leaves --seed 1``).
Three estimates run one after the other, each with the same workers: ``gainfpn estimate BURST
--preset balanced`` (the reference), the same with ``--method scene``, and the scene solver without
its calibrated confidence (``fit only``: the noise probe given no conjugate-gradient iteration and
the gain response taken as 1, so k is the fit's own and sigma_k is the fit's information alone, not
calibrated). One JSON line each: wall time, its ratio to ``balanced``'s, the residual gain FPN and
the bound (``gainfpn evaluate``), and the tenths of sigma_k. About 6 minutes at 4000x3000x8.

``tiles``: ``api.estimate(BURST, preset="balanced")`` with the scene solver on one worker, the time
of each tile's fit, noise probe and gain response summed over the tiles, with their conjugate-
gradient iterations, and of the whole tile (a 1536x1024x8 burst: about a minute).
"""

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gainfpn_cli.solve import scene


def without_confidence() -> None:
    """The scene solver's tiles, in this process, without the noise probe's iterations and the gain response."""
    scene.PROBE_STOPS = (0, 0, 0)
    scene._gain_response = lambda fit, a, est, unpull, rng, opt: (np.ones(a.size), 0)


if __name__ != "__main__":  # a spawned solver process of the ``fit only`` run
    without_confidence()

GAINFPN = str(Path(sys.executable).with_name("gainfpn"))
RUNS = {
    "balanced": [GAINFPN, "estimate", "--preset", "balanced"],
    "scene": [GAINFPN, "estimate", "--preset", "balanced", "--method", "scene"],
    "fit only": [sys.executable, __file__, "--fit-only", "estimate", "--preset", "balanced", "--method", "scene"],
}


def main(burst: Path, out: Path) -> None:
    reference = None
    for name, command in RUNS.items():
        target = out / name.replace(" ", "_")
        t0 = time.perf_counter()
        subprocess.run([*command, str(burst), "-o", str(target), "--overwrite", "-q"], check=True)
        seconds = time.perf_counter() - t0
        reference = reference or seconds
        scores = json.loads(subprocess.run([GAINFPN, "evaluate", str(target), "--truth", str(burst), "--overwrite",
                                            "--json"], check=True, capture_output=True, text=True).stdout)
        print(json.dumps({"run": name, "seconds": round(seconds, 1), "ratio": round(seconds / reference, 2),
                          **{k: round(scores[k], 3) for k in ("residual_fpn_percent", "residual_bound_percent")},
                          "tenths": [round(v, 2) for v in scores["confidence_deciles"]]}), flush=True)


def tile_parts(burst: Path) -> None:
    """The scene solver's tiles on one worker, their parts timed in this process."""
    from gainfpn_cli import api

    spent = {name: [0.0, 0] for name in ("fit", "probe", "response", "tile")}

    def timed(name, function, iterations):
        def call(*args):
            t0 = time.perf_counter()
            result = function(*args)
            spent[name][0] += time.perf_counter() - t0
            spent[name][1] += iterations(result)
            return result

        return call

    scene.fit_tile = timed("fit", scene.fit_tile, lambda fit: 0 if fit is None else fit.iterations)
    scene._noise_probe = timed("probe", scene._noise_probe, lambda out: out[2])
    scene._gain_response = timed("response", scene._gain_response, lambda out: out[1])
    scene._solve_tile = timed("tile", scene._solve_tile, lambda out: out[2])
    t0 = time.perf_counter()
    api.estimate(str(burst), preset="balanced", solver__method="scene", solver__workers=1)
    print(json.dumps({"estimate_s": round(time.perf_counter() - t0, 1),
                      **{f"{name}_s": round(seconds, 2) for name, (seconds, _) in spent.items()},
                      **{f"{name}_iterations": its for name, (_, its) in spent.items()}}))


if __name__ == "__main__":
    if sys.argv[1] == "tiles":
        tile_parts(Path(sys.argv[2]))
    elif sys.argv[1] == "--fit-only":  # the CLI in this process, its solver processes patched above
        without_confidence()
        from gainfpn_cli.cli import main as cli

        cli(sys.argv[2:])
    else:
        burst = Path(sys.argv[1])
        main(burst, Path(sys.argv[2]) if len(sys.argv) > 2 else burst.with_name(burst.name + ".cost"))
