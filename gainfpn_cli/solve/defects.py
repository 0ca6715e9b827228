"""Defective photosites, found from the burst itself: readings that do not follow the scene
along the motion trajectories.

A healthy photosite reads ``y_t = a x_t + noise`` in frame ``t``, with ``x_t`` the scene it sees
there and ``a`` its gain, within a few percent of its plane's. The scene is predicted without the
photosite's own readings mattering, twice (:mod:`solve.predict`): by the median of the frames on
the reference's grid brought back onto frame ``t``'s (the camera moved, so one photosite lands on
a different scene point in each frame and the median drops it; where fewer than 4 frames see a
point, the borders, the median of the photosite's 8 neighbours in its plane), and by the mean of
the readings of the two photosites of other frames nearest the scene point (the "sharper"
prediction, not interpolated: less than half the median's error on an aliased plane, but
noisier). Each photosite gets

* its response, the median over frames of ``y_t / x_t``, and its score ``z``: the response's
  distance from the plane's median, in units of the robust spread of responses (gain FPN and
  prediction error; the plane's, or where larger the median over the 5x5 neighbourhood of the
  responses' distance from the plane's median: beside an edge or a border the prediction misses
  for every photosite around) and of the photosite's own scatter over the frames (at least the
  rounding's), in quadrature;
* the variance of its readings over the frames, against a healthy photosite's there.

Kinds, in the order they are tested (:data:`KINDS` gives the codes of ``gain_map.exr``'s
``defect`` channel):

* ``dead``: no response, or too little for the gain range: below :data:`LOW_RESPONSE` of the
  plane's (between :data:`DEAD_RESPONSE` and it, unless stuck), below :data:`DEAD_CEILING`
  in every frame, and ``z < -Z_DEFECT``, where the sharper prediction does not show a response or
  a scene too dark for one, or the deficit below; or, where fewer than :data:`MIN_FRAMES` frames
  are lit enough for a response, readings below the healthy response in every frame, by a
  deficit that weighs each frame as a fitted response does (lit frames most; :func:`_dark_scores`,
  ``< -Z_DEFECT``, and below ``-Z_DEFECT / 2`` against the sharper prediction: beside a bright
  edge the median's error fakes both);
* ``stuck``: one reading (to a quantisation step) in every frame, where a healthy photosite's
  would vary more than :func:`stuck.quantised_steps` quantisation steps, by more than 1 /
  :data:`stuck.STUCK_SPREAD` times as much (in RMS) (the smaller of its 8 neighbours' and the scene's
  along its trajectory plus the noise at its level), unless both the reading and the scene are
  about black;
* ``hot``: a response far above the plane's, ``z > Z_DEFECT`` (``BORDER_Z`` times that where
  fewer than :data:`MIN_FRAMES` frames predict it from the other frames), and above it in every frame (a
  dark-current offset seen as a gain: where the scene along its trajectory is flat, an offset
  and a gain cannot be told apart from the burst, and one smaller than the plane's gain spread
  goes unseen; a dark frame finds those, ``input.dark``); or an offset far above the plane's in
  a fit of gain and offset to its readings (:func:`offset_scores`, ``> Z_OFFSET``, and ``>
  Z_SHARP_OFFSET`` against the sharper prediction): a trajectory across an edge tells an offset
  from a gain where the ratio's scatter over the frames hides it from the response; or readings far
  above the scene in every frame too dark for a response, at least :data:`MIN_FRAMES` of them
  (:func:`_dark_scores`, ``> Z_DEFECT``, and above ``Z_DEFECT / 2`` against the sharper prediction:
  a stuck or hot photosite in a black region); or, on a CFA colour's plane, an offset far above a
  control lattice's against a latent scene fitted without the likeliest hot photosites
  (:mod:`solve.leftout`).

Abnormally noisy photosites are not flagged: at scene edges of an aliased plane the prediction's
error scatters a healthy photosite's readings as much (docs/limits.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..metrics import MAD_TO_SIGMA
from .along import MIN_FIT_FRAMES, local_median, offset_scores, responses, robust_spread
from .leftout import left_out_hot
from .noise import NoiseModel
from .noise import fit as fit_noise
from .noise import level_and_scatter
from .predict import nearest_along, scene_along
from .stacks import Relative, each_strip, nan_median
from .stuck import quantisation_step, stuck_photosites
from .tiling import power_of_two_scale

#: Codes of the ``defect`` channel of ``gain_map.exr``: 0 is a healthy photosite.
HEALTHY, HOT, DEAD, STUCK = 0, 1, 2, 3
KINDS = {"hot": HOT, "dead": DEAD, "stuck": STUCK}

#: A photosite that gives less than this fraction of its plane's response is dead.
DEAD_RESPONSE = 0.25
#: ... and one under this fraction is coded dead too, unless it reads one value in every frame
#: (stuck): a gain the default range does not hold (solver.gain_range, k at most 2). Stuck
#: photosites reading 0.3-0.5 of a flat scene, which 8-bit noise does not tell from constant, were
#: left at 0.25 (docs/bench/defects.py, 8-bit at 75 %: stuck found 74-89 % -> 81-90 %; healthy
#: photosites flagged on its 80 photograph bursts 25 -> 29).
LOW_RESPONSE = 0.5
#: ... and less than this in every frame: a healthy photosite beside a sharp edge that the
#: prediction misses reads dark in some frames only (a dead one reads its noise, which at the
#: lowest level tested, MIN_LEVEL, is up to ~0.3 of it).
DEAD_CEILING = 0.5
#: Score (in standard deviations) past which a response is a defect's: the tails are heavier than
#: a Gaussian's (prediction errors at edges). Measured on 6 defect-free 240x320 raw12 dead-leaves
#: bursts (true motion, 8 frames, seeds 10-15): 6 flagged 0-0.13e-4 of the healthy photosites, 7
#: none; on the same kind of bursts with 0.5 % defects (docs/bench/defects.py) 6 finds 34 % of
#: the simulated hot ones, 7 31 %.
Z_DEFECT = 6.0
#: Fewest frames a photosite is tested on: with fewer, a median and a spread are too uncertain.
MIN_FRAMES = 4
#: A hot response where fewer than MIN_FRAMES of the frames it is tested on predict the photosite
#: from the other frames (the borders, where the 8 neighbours' median does, and around saturated
#: or excluded readings) needs this many times Z_DEFECT. Measured on ten defect-free 144x176 raw12
#: dead-leaves bursts of 5 frames (seeds 20-29): 40 of the 47 healthy photosites flagged were hot
#: within 7 px of the frame's edge; with 2, 18 flagged in all (0.71e-4), and the table of
#: docs/bench/defects.py lost 0-3 percentage points of the hot photosites found.
BORDER_Z = 2.0
#: Score of an offset fitted with the gain (:func:`offset_scores`) past which a photosite is hot.
#: Measured (docs/bench/defects.py, 240x320, 0.5 % defects and the same bursts without): at 8 and
#: 7 alike, at most 0.07e-4 of the healthy photosites flagged over the table's bursts of 8
#: frames, 7 finding 1-4 % more of the hot ones; 8 keeps a margin for scenes not tuned on.
Z_OFFSET = 8.0
#: The same against the sharper prediction (its scores in units of their own spread over the
#: plane), whose noisier fit flags more healthy photosites. Over 80 defect-free 144x176 bursts of
#: 6 and 7 frames (raw12 dead leaves 75 % and 7.5 %, procedural 75 %; 8-bit dead leaves 75 %) 8 /
#: 9 / 10 flagged 45 / 32 / 24 (26 with the median's tests alone), and found 65 / 60 / 57 % of the hot
#: photosites of the 8-frame raw12 dead-leaves bursts at 75 % (42 % without it).
Z_SHARP_OFFSET = 9.0
#: Scene levels below this fraction of the plane's bright level (99th percentile) do not enter
#: a response: near black, a ratio is all noise.
MIN_LEVEL = 0.02
#: ... nor below this many quantisation steps: a ratio of counts 1 or 2 is all rounding.
LEVEL_STEPS = 3.0
#: Reference peaks between which the search runs on the readings as they are; past them a stack is
#: divided by a power of two near its level first. float32 holds squares up to 2**128 and down to
#: 2**-126: the variances of readings near 2**64 overflow, and those of readings near 2**-63 underflow.
SAFE_PEAK = (2.0**-32, 2.0**32)


def detect(frames: np.ndarray, warp, *, saturation: float | None = None, excluded: np.ndarray | None = None,
           exposures: np.ndarray | None = None, aperture: float = 1.0, latent: bool = True,
           threads: int = 1) -> np.ndarray:
    """Defect code of every photosite of one plane, ``(H, W)`` uint8 (:data:`KINDS`): :func:`survey`'s."""
    return survey(frames, warp, saturation=saturation, excluded=excluded, exposures=exposures, aperture=aperture,
                  latent=latent, threads=threads).codes


@dataclass(frozen=True)
class Survey:
    """One plane's defect codes ``(H, W)`` uint8 (:data:`KINDS`) and its readings' noise against
    level, in the frames' units (None where nothing could be tested: too few frames)."""

    codes: np.ndarray
    noise: NoiseModel | None


def survey(frames: np.ndarray, warp, *, saturation: float | None = None, excluded: np.ndarray | None = None,
           exposures: np.ndarray | None = None, aperture: float = 1.0, latent: bool = True,
           threads: int = 1) -> Survey:
    """The defects of one plane and the noise of its readings.

    ``frames`` ``(F, H, W)`` are as read (black subtracted); ``exposures`` ``(F,)``, each frame's
    exposure relative to the reference's, brings them to the reference's (a stuck photosite reads
    one value as read, not after). ``warp`` maps between their grids (``pair(s, t,
    region)``, :mod:`geometry.warps`), ``excluded`` ``(F, H, W)`` marks readings that do not follow
    it (moving objects), ``aperture`` is a photosite's width in plane pixels (0.5 on a CFA colour's
    plane: :class:`solve.scene.SceneOptions`); ``latent``: on such a plane, the likeliest hot
    photosites tested again against a latent scene fitted without them (:mod:`solve.leftout`, from
    :data:`MIN_FIT_FRAMES` frames). Fewer than :data:`MIN_FRAMES` frames: all healthy, noise
    unknown. The statistics along the frames run a strip of rows at a time on ``threads`` threads
    (the same result on any number).
    """
    read = np.asarray(frames, np.float32)
    peak, unit = float(np.max(read[0], initial=0.0)), 1.0
    if peak > 0 and not SAFE_PEAK[0] <= peak <= SAFE_PEAK[1]:  # exact (a power of two), a copy only here
        unit = power_of_two_scale(read[0])
        read = read / np.float32(unit)
        saturation = None if saturation is None else saturation / unit  # in the same units
    frames = read if exposures is None else Relative(read, np.asarray(exposures, np.float32))
    n_frames, h, w = frames.shape
    codes = np.zeros((h, w), np.uint8)
    if n_frames < MIN_FRAMES:
        return Survey(codes, None)

    def good(t: int, frame: np.ndarray) -> np.ndarray:  # frame t's readings below saturation, following the motion
        below = frame < (np.inf if saturation is None else saturation)
        return below if excluded is None else below & ~excluded[t]

    x, valid, from_frames = scene_along(frames, good, warp, threads=threads)
    step = quantisation_step(read)
    # (the masked copy sorted in place: one copy of the stack's valid readings, not two)
    floor = max(MIN_LEVEL * float(np.quantile(x[valid], 0.99, overwrite_input=True)) if valid.any() else 0.0,
                LEVEL_STEPS * step)
    usable = valid & (x > floor)
    always = valid.all(axis=0)  # every reading usable as far as the frames and the motion go
    from_frames &= valid  # (in place: no third stack) the valid readings the other frames predict
    del valid  # frame-stack-sized, as usable and from_frames are
    response, scatter, n, lowest, highest, level = responses(frames, x, usable, threads)
    tested = n >= MIN_FRAMES
    if not tested.any():
        return Survey(codes, None)
    # the plane's spread, or its neighbourhood's where larger: beside an edge or a border the
    # prediction misses, consistently over the frames, for every photosite around
    typical, plane_spread, spread = robust_spread(response, tested)
    z = _scores(response, typical, spread, scatter, n, tested)
    dead = tested & (response < LOW_RESPONSE * typical) & (highest < DEAD_CEILING * typical) & (z < -Z_DEFECT)
    silent = dead & (response < DEAD_RESPONSE * typical)  # dead whatever its readings' spread
    whole = usable.all(axis=0) & ~silent
    noise = fit_noise(*level_and_scatter(frames, x, response, whole, threads=threads), n_frames)
    stuck = stuck_photosites(frames, read, always, x, typical, noise, step, floor, threads)
    usable &= from_frames  # from here on, only readings the other frames predict
    # where the scene is too dark for a response: readings far above it, or below it, in every frame (at
    # Z_DEFECT: on defect-free 144x176 bursts of 5-7 frames 0-3 more flags per 253 440 photosites)
    dim = _dark_scores(frames, x, from_frames, usable, typical, plane_spread, noise, threads)
    # a response's own scatter at least the rounding's: near black, where most readings of a photosite
    # are one count, their median absolute deviation can be 0
    rounding = step / np.sqrt(12) / np.maximum(level, 1e-30)
    z = _scores(response, typical, spread, np.maximum(scatter, rounding), n, tested)
    hot = (z > np.where(usable.sum(axis=0) >= MIN_FRAMES, Z_DEFECT, BORDER_Z * Z_DEFECT)) & (lowest > typical)
    if n_frames >= MIN_FIT_FRAMES:
        hot |= offset_scores(frames, x, usable, typical, plane_spread, scatter, noise, threads) > Z_OFFSET
    # (the stacks and planes no longer needed: the sharper prediction's in their place)
    del x, usable, from_frames, response, scatter, lowest, highest, level, z, rounding, spread
    sharp = _sharp_tests(frames, good, warp, floor, noise, typical, plane_spread, stuck, threads)
    # beside a bright edge the median's error fakes a dead response and a dim photosite's readings
    # far from its scene; the sharper prediction's, less than half of it there, seldom: each is
    # confirmed by it, a dim one at half the score (that prediction is the noisier: at the full
    # score the 8-bit dark dead leaves of docs/bench/defects.py lost 3 % of their dead photosites,
    # at half none); a dead response whose frames are mostly dim by the deficit of them all too
    dim = np.where((dim * sharp.dim > 0) & (np.abs(sharp.dim) > Z_DEFECT / 2), dim, 0)
    dead &= sharp.unlit | (dim < -Z_DEFECT)
    stuck &= sharp.lit | (read[0] > floor)
    if n_frames >= MIN_FIT_FRAMES:
        hot |= sharp.offsets > Z_SHARP_OFFSET
    if latent and n_frames >= MIN_FIT_FRAMES and aperture < 1:
        # on a CFA colour's plane, the likeliest hot photosites against a latent scene fitted without
        # them (solve.leftout: one fit of the scene model, about 2x the rest of the search's time; a
        # monochrome plane's are tested so where the scene solver runs, defective.offset_shown)
        hot |= left_out_hot(frames, read, warp, sharp.response, tested=sharp.tested, noise=noise, floor=floor,
                            aperture=aperture, good=good, exposures=exposures, threads=threads)
    stuck &= ~(silent & dead)
    dead &= ~stuck
    hot &= tested & ~dead & ~stuck
    hot |= ~dead & ~stuck & (dim > Z_DEFECT)
    dead |= ~tested & ~stuck & (dim < -Z_DEFECT)
    for mask, code in ((dead, DEAD), (stuck, STUCK), (hot, HOT)):
        codes[mask] = code
    return Survey(codes, noise.scaled(unit))


def _scores(response, typical: float, spread: np.ndarray, scatter, n, tested) -> np.ndarray:
    """Each photosite's score ``z``: its response's distance from the ``typical`` one over the
    ``spread`` (:func:`robust_spread`'s, per photosite) and its own ``scatter`` over its ``n``
    frames, in quadrature."""
    # the median of n ratios scatters pi/2 times as much (in variance) as their mean; a scatter
    # from a few frames can be small by chance: not below its neighbourhood's (prediction errors
    # near an edge are shared by the photosites along it)
    local = local_median(np.where(tested, scatter, 0.0))
    own = np.pi / 2 * np.maximum(scatter, local) ** 2 / np.maximum(n, 1)
    return np.where(tested, (response - typical) / np.sqrt(spread**2 + own + 1e-30), 0.0)


class _Sharp(NamedTuple):
    """What the sharper prediction tells, per photosite (:func:`_sharp_tests`)."""

    offsets: np.ndarray | None  # offset_scores against it (None under MIN_FIT_FRAMES frames)
    response: np.ndarray  # the median ratio of reading to it, where at least MIN_FRAMES are predicted
    tested: np.ndarray
    dim: np.ndarray  # _dark_scores against it
    unlit: np.ndarray  # its response under LOW_RESPONSE of the plane's, or fewer than MIN_FRAMES predicted
    lit: np.ndarray  # at the photosites asked: the median scene along the trajectory above the floor


def _sharp_tests(frames, good, warp, floor: float, noise, plane_typical: float, plane_spread: float,
                 asked: np.ndarray, threads: int = 1) -> _Sharp:
    """The tests that the median prediction's error beside a sharp edge of an aliased plane spoils,
    against the sharper prediction (:func:`predict.nearest_along`, less than half its error):
    it fakes a dead photosite's response, and a dim one's readings far from the scene
    (:func:`_dark_scores`), where this one does not; and it hides offsets (:func:`offset_scores`)
    that this one shows. Over the readings above ``floor``, as the median's; whether the scene is
    above it along the trajectory, at the photosites ``asked`` (those read as stuck)."""
    x, valid = nearest_along(frames, good, warp, threads=threads)
    usable = x > floor
    usable &= valid
    dim = _dark_scores(frames, x, valid, usable, plane_typical, plane_spread, noise, threads)
    seen = valid.sum(axis=0) >= MIN_FRAMES  # (not tested there: too dark for a response)
    lit = ~seen
    lit[asked] |= nan_median(np.where(valid[:, asked], x[:, asked], np.float32(np.nan))) > floor
    del valid
    response, scatter, n, *_ = responses(frames, x, usable, threads)
    tested = n >= MIN_FRAMES
    if not tested.any():
        return _Sharp(np.zeros(tested.shape), response, tested, dim, ~seen, lit)  # (no response: no offset either)
    typical, spread, _ = robust_spread(response, tested)
    fit = frames.shape[0] >= MIN_FIT_FRAMES
    offsets = offset_scores(frames, x, usable, typical, spread, scatter, noise, threads) if fit else None
    return _Sharp(offsets, response, tested, dim, ~seen | (tested & (response < LOW_RESPONSE * typical)), lit)


def _dark_scores(y: np.ndarray, x: np.ndarray, valid: np.ndarray, usable: np.ndarray, typical: float,
                 spread: float, noise, threads: int = 1) -> np.ndarray:
    """Per photosite, its readings' mean excess over the healthy response ``typical x_t`` in the
    ``valid`` frames not ``usable`` (where the scene is too dark for a ratio), over its standard
    error (negative for a deficit): the noise at the brightest of those frames' levels over the
    number of frames with the gains' ``spread`` at that level, or where larger the robust spread
    over the 5x5 neighbourhood of every photosite's mean excess in all its ``valid`` frames (beside
    a sharp edge the interpolated prediction rings, below black in places, and healthy readings
    there exceed it by hundreds of DN); 0 where fewer than :data:`MIN_FRAMES` frames are dim or the readings are not all above
    (or all below) their healthy response. Or, lower, where every ``valid`` reading (at least
    :data:`MIN_FRAMES`) is below its healthy response, that deficit as a response fitted over them
    all would show it: ``sum x_t (y_t - typical x_t) / v_t`` over its standard error, ``v_t`` the
    noise at ``x_t``, the gains' ``spread`` counted. A stuck or hot photosite in a black region reads
    far above what any healthy one there can (a stuck reading of 200 where the scene gives 3
    counts), a dead one below it in every frame (0 where the scene gives 2-5 counts, or 15 in the
    one frame its trajectory crosses a lit patch)."""
    # two passes a strip at a time (on ``threads`` threads): a plane's temporaries, not a stack's
    overall = np.zeros(y.shape[1:], np.float32)

    def mean_excess(rows):
        known = valid[:, rows]
        seen = known.sum(axis=0)
        total = np.where(known, y[:, rows] - typical * x[:, rows], np.float32(0)).sum(axis=0)
        overall[rows] = np.where(seen >= MIN_FRAMES, np.abs(total) / np.maximum(seen, 1), 0)

    each_strip(mean_excess, y.shape, threads=threads)
    around = (MAD_TO_SIGMA * local_median(overall)).astype(np.float32)
    overall = None  # let go (a plane; the pass's closure holds its cell)
    score = np.zeros(y.shape[1:], np.float32)

    def dim_score(rows):
        use = valid[:, rows] & ~usable[:, rows]
        count = use.sum(axis=0)
        over = y[:, rows] - typical * x[:, rows]
        excess = np.where(use, over, 0).sum(axis=0) / np.maximum(count, 1)
        lowest = np.where(use, over, np.float32(np.inf)).min(axis=0)
        highest = np.where(use, over, np.float32(-np.inf)).max(axis=0)
        brightest = np.where(use, x[:, rows], np.float32(0)).max(axis=0)
        own = np.sqrt(noise(np.maximum(brightest, 0.0)) / np.maximum(count, 1) + (spread * brightest) ** 2)
        sure = (count >= MIN_FRAMES) & ((lowest > 0) | (highest < 0))
        score[rows] = np.where(sure, excess / np.maximum(np.maximum(own, around[rows]), 1e-12), 0.0)
        # a dead photosite's deficit grows with the scene: its response fitted over every frame, lit
        # and dim, each weighted by x / v, against the healthy one (the gains' spread counted)
        # (only where every reading is below it: a few photosites, not the strip's stack)
        every = valid[:, rows]
        at = np.nonzero((every.sum(axis=0) >= MIN_FRAMES) & (np.where(every, over, -np.inf).max(axis=0) < 0))
        if not at[0].size:
            return
        known = every[:, at[0], at[1]]
        lit = np.where(known, x[:, rows][:, at[0], at[1]], np.float32(0)).astype(np.float64)
        weight = lit / np.maximum(noise(np.maximum(lit, 0.0)), 1e-30)
        information = (weight * lit).sum(axis=0)
        deficit = (weight * np.where(known, over[:, at[0], at[1]], 0)).sum(axis=0)
        dead = deficit / np.sqrt(information + (spread * information) ** 2 + 1e-30)
        part = score[rows]  # (a view: written through)
        part[at] = np.minimum(part[at], dead)

    each_strip(dim_score, y.shape, threads=threads)
    return score
