"""The hold-out check of a solved burst: the map fitted again without the reference on the central
region of every grid, its residual on the held-out frame with k over without (:mod:`solve.holdout`),
the grids it rejects and their warning.

:mod:`pipeline` runs it after :mod:`solving` has solved the planes.
"""

from __future__ import annotations

from . import solving
from .report import Holdout, PlaneCheck
from .solve.holdout import disagreement, holdout_checks, pooled

#: The hold-out check keeps a plane's estimate only where its residual ratio is below 1 by this many
#: standard errors (one-sided, 2.3 % of estimates that do not help would pass by chance at one look).
CHECK_Z = 2.0
#: A grid whose check is inconclusive (ratio below 1, but not by CHECK_Z standard errors) on a region
#: smaller than the grid is checked again on one this many times as wide: 4x the pixels, half the
#: standard error, at 4x the check's cost only where the first look could not decide. Measured on the
#: bench's 640x480x8 burst, the paper's 3x3 blocks (MSE 2.7x): 0.888 +- 0.058 on 256 px, 0.932 +- 0.032
#: on 512 px. A map that does nothing then passes by chance 3.9 % of the time, not 2.3 % (simulated:
#: two normal ratios correlated 0.5, as a region's and its centre quarter's are).
WIDER = 2


def check(burst, frames, excluded, exposures, n_fit, in_frame, solver: solving.Solver, reports, calibrations,
          progress, held_out: str, k, confidence):
    """The hold-out check (:mod:`solve.holdout`) of the map ``k`` (``confidence``) of every grid on the
    frame named ``held_out``, and the grids it rejects.

    k is fitted again on the central :data:`solving.CHECK_SIDE` px of each grid, from the fitted frames
    without the reference and with each plane's FPN model and calibration as for ``k``, so that
    neither frame the check compares is in it; grids that region leaves undecided are checked again
    on one :data:`WIDER` times as wide."""
    grids = solving.grids_of(burst, frames, solver.method)

    def look(side: int, names) -> dict:
        """The check of the grids ``names`` on their central ``side`` px."""
        regions = {name: r for name, r in solving.central(burst, frames, solver, side).items() if name in names}
        fitted = solving.solve_planes(
            burst, frames, excluded, exposures, slice(1, n_fit), in_frame, solver, progress,
            regions={name: [region] for name, region in regions.items()},
            models={name: p.fpn_model for name, p in reports.items()}, calibrations=calibrations)
        k_check, confidence_check = fitted.k, fitted.confidence
        return holdout_checks(frames, excluded, exposures, in_frame, k_check,
                              grids=[grid for grid in grids if grid.name in names], saturation=burst.saturation,
                              regions=regions, disagreement=disagreement(k_check, confidence_check, k, confidence,
                                                                         calibrated=solver.calibrated),
                              columns=[grid.name for grid in grids if column_gains(reports, grid)])

    checks = look(solving.CHECK_SIDE, [grid.name for grid in grids])
    sides = dict.fromkeys(checks, solving.CHECK_SIDE)
    undecided = [grid.name for grid in grids if not checks[grid.name].passed(CHECK_Z)
                 and checks[grid.name].ratio < 1 and max(grid.shape) > solving.CHECK_SIDE]
    if undecided:
        checks.update(look(WIDER * solving.CHECK_SIDE, undecided))
        sides.update(dict.fromkeys(undecided, WIDER * solving.CHECK_SIDE))
    failed = [grid for grid in grids if not checks[grid.name].passed(CHECK_Z)]
    if short_mosaic(burst, n_fit):  # what the check confirms there is not to be trusted (short_mosaic)
        failed = grids
    every = pooled(checks.values())
    planes = {name: PlaneCheck(c.ratio, c.standard_error, c.passed(CHECK_Z), c.left_out, sides[name])
              for name, c in checks.items()}
    return Holdout(held_out, every.ratio, len(failed) < len(grids), every.standard_error, planes), failed


def column_gains(reports, grid) -> bool:
    """Whether the map of a plane of ``grid`` is built on a gain per column (its FPN model, or the one
    its pixel model shrinks toward): the hold-out check then leaves out a column of blocks at a time
    (:func:`solve.holdout.column_strips`). The ``row`` models' gain per row parity is in every block."""
    return any("column" in (reports[name].fpn_base or "") for name in grid.positions if name in reports)


def short_mosaic(burst, n_fit: int) -> bool:
    """Whether a burst fitted on ``n_fit`` frames is a CFA mosaic too short for the check to be trusted.

    With fewer than :data:`solving.MIN_SPLIT_FRAMES` fitted frames no halves measure a colour plane's
    sigma_k (and the burst the scene model predicts lacks the plane's aliasing), and on such bursts the
    check confirmed maps worse than none: 240x320 12-bit RGGB bursts of 5 and 6 frames, 1 % pixel FPN
    (docs/limits.md, "Few frames"), 10 of 40 maps accepted, 3 of them worse than none on an unseen frame
    (the photograph ``camera`` at a mean of 40 % of full scale, 5 frames: 0.63x) and 8 with a tenth of
    their sigma_k 1.29-2.92x too low."""
    return burst.cfa is not None and n_fit < solving.MIN_SPLIT_FRAMES


def rejection(holdout: Holdout, failed, burst, n_fit: int) -> str:
    """The warning of planes the hold-out check rejected (``failed``, of a burst fitted on ``n_fit``
    frames): what was written, why, and what would help."""
    if short_mosaic(burst, n_fit):
        return (f"a CFA mosaic fitted on {n_fit} frames: with fewer than {solving.MIN_SPLIT_FRAMES} no two halves "
                f"of them measure how far k errs, and the hold-out frame alone lets maps worse than none through, "
                f"so k = 1 (no correction) was written (residual ratio with k over without "
                f"{holdout.residual_ratio:.3f}), and its PRNU is not reported; capture {solving.MIN_SPLIT_FRAMES + 1} "
                f"or more frames, or set output.holdout: false to fit all {n_fit + 1} unchecked (their confidence "
                f"then not calibrated)")
    which = "the estimate" if len(failed) == len(holdout.planes) else "the " + ", ".join(g.name for g in failed)
    ratios = ", ".join(f"{g.name} {holdout.planes[g.name].residual_ratio:.3f} +- "
                       f"{holdout.planes[g.name].standard_error:.3f}" for g in failed)
    return (f"the hold-out frame does not confirm {which} (residual ratio with k over without: {ratios}; a "
            f"correction is kept only below 1 by {CHECK_Z:g} standard errors), so k = 1 (no correction) was written "
            f"there: the burst is too noisy or too aliased for its gain pattern; more frames, more light or more "
            f"motion would help")
