"""``solver.method: auto``: the solver a burst needs (docs/method.md section 8c). The scene model
where interpolating one frame from another leaves more error than noise and gain FPN explain (an
aliased burst), the pairwise form elsewhere and on CFA mosaics; with few frames both, the map of
the lower expected error kept.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .report import SolverChoice
from .solve.aliasing import aliasing
from .solve.result import sigma_from_confidence
from .solve.tiling import usable
from .solving import Solver, central, grids_of


#: ``solver.method: auto`` models the latent scene (the scene method) where the pairwise prediction
#: error exceeds the noise's by this fraction or more (:mod:`solve.aliasing`). Measured on 640x480x8
#: paper bursts (docs/method.md section 8c): dead leaves 0.24 (scene 1.51x the bound, accurate
#: 2.15x); procedural 0.013, camera -0.05, brick -0.05, where the accurate method is as good or better.
ALIASED = 0.1
#: ... with this many frames fitted or more: a latent scene at twice the pixel pitch takes 4
#: readings' worth of information per pixel, ``sqrt(T / (T - 4))`` in sigma_k (1.53 at 7 frames:
#: an 8-frame burst with one held out, where the figures above were measured).
SCENE_MIN_FRAMES = 7
#: With fewer, from this many, both solvers are run on an aliased burst and the one expected to err less
#: (:func:`expected_error`) is kept: the scene's noise costs more than the aliasing on dark bursts.
#: Measured on 240x320 paper dead leaves of 5 / 6 frames (4 / 5 fitted, seeds 3-5 / 3-4): at 75 %
#: exposure the scene solver's MSE ratio on an unseen frame is 1.6-1.9x the accurate one's; at 15 %
#: 0.90-0.97x; the expected error ranks them as the truth in all 10, the hold-out ratio in 9 (method.md 8c).
SCENE_TRIAL_FRAMES = 4


def choose(burst, frames, excluded, exposures, used: slice, in_frame,
           solver: Solver) -> tuple[Solver, SolverChoice]:
    """The solver ``solver.method: auto`` resolves to for this burst, and why; any other method as it is."""
    if solver.method != "auto":
        return solver, SolverChoice(solver.method, "set by solver.method")
    choice = _auto(burst, frames, excluded, exposures, used, in_frame, solver)
    return dataclasses.replace(solver, method=choice.method), choice


def _auto(burst, frames, excluded, exposures, used: slice, in_frame, solver: Solver) -> SolverChoice:
    fitted = len(range(len(frames))[used])
    if burst.cfa is not None:
        return SolverChoice("accurate", "a CFA mosaic: each colour's latent scene would be sampled at the photosite "
                            "pitch, which a colour plane itself sees only every other photosite (still aliased), so "
                            "the pairwise form is used")
    if fitted < SCENE_TRIAL_FRAMES:
        return SolverChoice("accurate", f"{fitted} frames fitted: too few for a latent scene at twice the pixel "
                                        f"pitch (at least {SCENE_TRIAL_FRAMES})")
    measured = _most_aliased(burst, frames, excluded, exposures, used, in_frame, solver)
    if measured is None:
        return SolverChoice("accurate", "the aliasing could not be measured (too few pixels seen by enough frames), "
                                        "so the pairwise form is used")
    method, verdict = ("scene", "aliased") if measured >= ALIASED else ("accurate", "not aliased")
    reason = (f"{verdict}: predicting one frame from another by interpolation leaves {100 * (1 + measured):.0f} % "
              f"of the error that noise and gain FPN explain (the scene model from {100 * (1 + ALIASED):.0f} %)")
    if method == "scene" and fitted < SCENE_MIN_FRAMES:
        return SolverChoice("accurate", f"{reason}; with {fitted} frames fitted (fewer than {SCENE_MIN_FRAMES}) the "
                                        "latent scene's noise can cost more than the aliasing, so both solvers are "
                                        "run and the one expected to err less is kept where the hold-out frame "
                                        "confirms the accurate one", measured,
                            ("accurate", "scene"))
    return SolverChoice(method, reason, measured)


def tried(choice: SolverChoice, ratios: dict, errors: dict, method: str, confirmed: bool) -> SolverChoice:
    """``choice`` (whose ``tried`` methods were run, the accurate one first) with the method kept, each
    method's hold-out residual ratio (``ratios``, method -> ratio) and expected error (``errors``, method ->
    :func:`expected_error`), and whether the check ``confirmed`` the accurate solver's map, in its reason."""
    told = ", ".join(f"{m} {r:.3f}" for m, r in ratios.items())
    expected = ", ".join(f"{m} {100 * e:.2f} %" for m, e in errors.items())
    why = "" if confirmed else (" (the check does not confirm the accurate solver's map: on data this weak the "
                                "scene solver's sigma_k is not calibrated with few frames)")
    return dataclasses.replace(choice, method=method, reason=f"{choice.reason}: residual ratio {told}; expected "
                                                            f"error {expected}; {method} kept{why}")


def expected_error(confidence: np.ndarray, level: np.ndarray, fpn: float) -> float:
    """The RMS error a written map is expected to leave in a frame at ``level`` (per pixel, the
    frame's shape), weighted as the frame's squared error is (by ``level^2``): its ``sigma_k`` where it
    has a gain, the input pixel FPN ``fpn`` where it writes k = 1.

    Which of two calibrated maps to keep: on 21 240x320 paper bursts of 5-6 frames (dead leaves at
    75 % and 15 % exposure, seeds 3-5 and 7; photographs at 40 % and 7.5 % of full scale) the lower
    kept the map of the better MSE ratio on an unseen frame in 20 (the miss cost 4 %); the lower
    hold-out ratio in 17 (dark dead leaves: 7 and 11 %; docs/method.md section 8c)."""
    sigma = np.where(confidence > 0, sigma_from_confidence(np.where(confidence > 0, confidence, 1)), fpn)
    weight = np.where(np.isfinite(level) & (level > 0), np.asarray(level, np.float64) ** 2, 0.0)
    total = float(weight.sum())
    return float(np.sqrt(np.sum(weight * sigma.astype(np.float64) ** 2) / total)) if total > 0 else float("inf")


def _most_aliased(burst, frames, excluded, exposures, used: slice, in_frame, solver: Solver) -> float | None:
    """The largest aliasing excess (:func:`solve.aliasing.aliasing`) over the planes' central regions, of
    the frames ``used``; None if no plane's could be measured."""
    fit = frames[used]  # a slice: a view
    left_out = None if excluded is None else np.broadcast_to(excluded[used, ..., None], fit.shape)  # every channel
    regions = central(burst, frames, solver)
    motion = in_frame.select(range(len(frames))[used])
    measured = []
    for grid in grids_of(burst, frames, "accurate"):
        plane = grid.gather(fit)
        good = usable(plane, burst.saturation, None if left_out is None else grid.gather(left_out))
        excess = aliasing(plane, motion.conjugate(grid.S), exposures=exposures[used], good=good,
                          region=regions[grid.name]).excess
        if excess is not None:
            measured.append(excess)
    return max(measured, default=None)
