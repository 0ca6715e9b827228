"""k's error measured on the burst the scene model predicts (a parametric bootstrap): what calibrates
the accurate solver's ``sigma_k`` where the frames are too few for two halves, and the least its
factors are where halves measure them (:func:`raised`; docs/method.md section 11).

With 3-5 frames fitted, most of k's error on a detailed scene is the pairwise model's (interpolating
detail no kernel predicts), and the fit takes it up: it does not show in the residuals the solver's
``sigma_k`` is made of. The scene model (:mod:`solve.scenemodel`) explains the same readings from a
latent scene twice as fine as the pixels, so the burst it predicts holds the scene's detail as the
frames see it. That burst is rendered with a known gain (the estimate's own ``1 / k``) and a draw of
the fitted noise model, solved again by the pairwise solver, and its error measured against that
gain: per tenth of the real fit's ``sigma_k``, its RMS over the RMS ``sigma_k`` scales the real
``sigma_k``, as the halves' Hausman difference does with more frames. Pure array functions; the
planes and regions are :mod:`solving`'s.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .halves import MAX_PARTS, MIN_PARTS, PART_PIXELS, Calibration
from .scene import prepare
from .scenemodel import fit_tile
from .tiling import Tile, power_of_two_scale, ramp_sums, solve_tiles


@dataclass(frozen=True)
class Rendered:
    """The readings a fitted scene model predicts for a burst, gains 1, the standard deviation of its
    noise model at each (``(F, H, W)`` float32, in the frames' units and at their exposures; 0
    where it does not see the reading), and where it sees them: inside its scene, and read by the
    fit (not clipped, at black or left out)."""

    readings: np.ndarray
    noise: np.ndarray
    seen: np.ndarray


def render_many(problems, *, options, workers: int = 2, progress=None, executor=None) -> list[Rendered]:
    """The burst the scene model fitted to each of ``problems`` predicts (dicts as for
    :func:`solve.scene.solve_scene_many`, each with its own ``options`` if it has them), every tile
    fitted in one go; tiles overlap as the solver's and are blended by the same ramps."""
    prepared = [prepare(p, options) for p in problems]
    shapes = iter([np.shape(p["frames"]) for p in problems])
    return solve_tiles(prepared, _render_tile, lambda tiles, results: _blend(tiles, results, next(shapes)),
                       workers=workers, progress=progress, executor=executor)


def _render_tile(tile: Tile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The readings of one tile (its halo included) its fitted model predicts, their noise's standard
    deviation and where it sees them."""
    shape = tile.frames.shape
    fit = fit_tile(tile)
    if fit is None or fit.noise is None:
        return np.zeros(shape, np.float32), np.zeros(shape, np.float32), np.zeros(shape, bool)
    # the fit's readings are the frames over a power of two, their exposures and its own refined ones
    # (scaled back as standard deviations, not variances: exact, and far from float32's limits)
    scale = power_of_two_scale(tile.frames.astype(np.float64)) * fit.exposure
    if tile.exposures is not None:
        scale = scale * np.asarray(tile.exposures)
    scale = np.repeat(scale, shape[1] * shape[2])
    noise = np.sqrt(np.maximum(fit.noise[0] + fit.noise[1] * np.abs(fit.predicted), 0.0)) * scale
    return (np.where(fit.valid, fit.predicted * scale, 0.0).reshape(shape).astype(np.float32),
            np.where(fit.valid, noise, 0.0).reshape(shape).astype(np.float32), fit.valid.reshape(shape))


def _blend(tiles: list[Tile], results, shape) -> Rendered:
    (readings, noise), weight = ramp_sums([(t.y0, t.x0) for t in tiles], results, lambda r: r[:2], lambda r: r[2],
                                          shape, tiles[0].options.halo)
    seen = weight > 0
    return Rendered(np.divide(readings, weight, out=np.zeros(shape, np.float32), where=seen),
                    np.divide(noise, weight, out=np.zeros(shape, np.float32), where=seen), seen)


def synthetic_burst(rendered: Rendered, gain: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``rendered``'s readings times ``gain`` (``(H, W)``) plus a draw of its noise, 0 (read as black:
    left out by the solvers) where it does not see a reading; a draw at or below 0 reads as black,
    as a sensor's does."""
    drawn = rendered.readings * np.asarray(gain, np.float32) \
        + rng.standard_normal(rendered.readings.shape).astype(np.float32) * rendered.noise
    return np.where(rendered.seen, np.maximum(drawn, np.float32(0)), np.float32(0))


def calibration(sigma: np.ndarray, error: np.ndarray, mask: np.ndarray) -> Calibration | None:
    """The :class:`solve.halves.Calibration` that scales ``sigma`` (a fit's ``sigma_k``) to the RMS of
    ``error`` (the same fit's error on a synthetic burst) in each tenth of ``sigma`` over ``mask``
    (fewer parts on fewer pixels, as :func:`solve.halves.calibrate`), never scaled down: the
    synthetic burst's noise is the share the scene model's fit left in its residuals, so a smaller
    error there is its noise missing, not ``sigma`` too large (docs/method.md section 11). Its pixel
    FPN prior is left to the deviations (None). None where too few pixels are measured."""
    use = mask & np.isfinite(sigma) & np.isfinite(error)
    count = min(int(use.sum()) // PART_PIXELS, MAX_PARTS)
    if count < MIN_PARTS:
        return None
    s, e = sigma[use].astype(np.float64), error[use].astype(np.float64)
    e = e - e.mean()  # the gauge: k's overall level is free
    log_sigma, factor = [], []
    for part in np.array_split(np.argsort(s), count):
        square = float(np.mean(s[part] ** 2))
        log_sigma.append(0.5 * np.log(square))
        factor.append(max(float(np.sqrt(np.mean(e[part] ** 2) / square)), 1.0))
    return Calibration(np.array(log_sigma), np.array(factor), None)


def raised(calibration: Calibration | None, floor: Calibration | None) -> Calibration | None:
    """The halves' ``calibration`` with its factor at least ``floor``'s at every ``sigma_k`` (the one
    :func:`calibration` measures on the burst the scene model predicts): the larger of the two at each
    sigma_k either measured at, so that the lines :meth:`Calibration.sigma` draws between them are
    above both; its prior kept; ``floor`` itself where the halves measured nothing.

    The halves' Hausman difference misses what both halves err alike (the pairwise model's error on
    the scene's detail, the motion estimate's), and so read factors under 1 where k erred 1.3-1.6x
    the solver's ``sigma_k``; the model's burst never reads under 1 and holds the first (not the
    second: it is rendered and fitted with the same warps). On 640x480 8-bit bursts of 16 frames
    (`balanced`) the least precise tenth erred 1.32x what the halves stated, raised 0.99x
    (docs/limits.md, "Confidence")."""
    if floor is None:
        return calibration
    if calibration is None or not calibration.measured:
        return floor
    at = np.union1d(calibration.log_sigma, floor.log_sigma)
    factor = np.maximum(np.interp(at, calibration.log_sigma, calibration.factor),
                        np.interp(at, floor.log_sigma, floor.factor))
    return dataclasses.replace(calibration, log_sigma=at, factor=factor)


def instead(calibration: Calibration | None, floor: Calibration | None) -> Calibration | None:
    """The halves' ``calibration`` with the factors ``floor`` measured on the burst the scene model predicts
    in place of its own, its prior kept: for a fit the halves' Hausman difference does not measure, one
    less precise than either half (:func:`solving.hausman_holds`)."""
    if floor is None:
        return calibration
    if calibration is None or not calibration.measured:
        return floor
    return dataclasses.replace(calibration, log_sigma=floor.log_sigma, factor=floor.factor)
