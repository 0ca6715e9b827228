"""Defective photosites: found from the burst (and a dark frame), left out, written, repaired."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from gainfpn_cli import api, defective
from gainfpn_cli.files import read_exr_planes, write_exr
from gainfpn_cli.geometry.cfa import plane_to_mosaic
from gainfpn_cli.geometry.planes import plane_views
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import hot_offset_z, response_z
from gainfpn_cli.solve import defects as D
from gainfpn_cli.solve import leftout, stacks
from gainfpn_cli.solve.scene import SceneOptions
from gainfpn_cli.solve.stuck import ONE_VALUE_CHANCE, QUANTISED_STEPS, one_value_chance, quantised_steps

RAW12 = PRESETS["raw12"]
MONO = dataclasses.replace(RAW12, cfa=None)


def _codes(burst, sensor, latent: bool = True) -> np.ndarray:
    """detect() on every plane of a simulated burst, with its true motion."""
    frames = (burst.frames.astype(np.float32) - sensor.black_level)[..., None]
    codes = np.zeros(frames.shape[1:3], np.uint8)
    for _, pick, S in plane_views(sensor.cfa, ("Y",)):
        pick(codes[..., None])[...] = D.detect(pick(frames), GlobalWarp(burst.homographies).conjugate(S),
                                               saturation=burst.saturation, aperture=0.5 if sensor.cfa else 1.0,
                                               latent=latent)
    return codes


@pytest.mark.parametrize("sensor, exposure", [(RAW12, 0.75), (RAW12, 0.075), (MONO, 0.3)])
def test_dead_and_stuck_photosites_are_found_and_healthy_ones_left_alone(sensor, exposure):
    kwargs = dict(shape=(240, 320), n_frames=8, sensor=sensor, scene="dead-leaves", exposure=exposure, seed=2)
    burst = simulate_burst(defects=0.005, **kwargs)
    codes = _codes(burst, sensor)
    for code in (D.DEAD, D.STUCK):  # 58 of each: every one flagged (measured 100 % on the bench)
        assert (codes[burst.defects == code] > 0).all()
    # hot ones where they stand out from the plane's gain spread (the larger offsets) or the scene
    # along their trajectory varies: 18-99 % of the simulated ones on the bench; here 68 / 91 / 85 %
    # (38 / 72 / 79 % against the median prediction alone, 59 / 85 / 85 % without the latent scene's
    # test of the RGGB planes, solve.leftout)
    assert (codes[burst.defects == D.HOT] > 0).mean() > 0.5
    clean = _codes(simulate_burst(**kwargs), sensor)
    assert np.count_nonzero(clean) <= 1e-4 * clean.size  # 7.7 photosites: 0-4 measured (Z_DEFECT)


@pytest.mark.parametrize("preset, exposure, share", [("paper", 0.75, 0.65), ("raw12", 0.075, 0.98)])
def test_hot_photosites_the_burst_shows_plainly_are_found(preset, exposure, share):
    # offsets the burst tells from a gain by 20 of their standard errors (with the scene known):
    # the detector before the fit of gain and offset along each trajectory found 38 % (8-bit) and
    # 65 % (RGGB, dark) of them on these bursts, with the fit 60 % and 81 %, with the fit against
    # the nearest readings' prediction too (solve.predict) 69 % and 96 %, with the RGGB planes' test
    # against a latent scene fitted without the suspects (solve.leftout) 69 % and 99.5 %
    sensor = PRESETS[preset]
    kwargs = dict(shape=(240, 320), n_frames=8, sensor=sensor, scene="dead-leaves", exposure=exposure, seed=2)
    burst = simulate_burst(defects=0.005, **kwargs)
    hot = burst.defects == D.HOT
    plain = hot_offset_z(burst, sensor, hot) > 20
    assert plain.sum() >= 30  # 42 and 210: enough for a share
    assert (_codes(burst, sensor)[hot][plain] > 0).mean() >= share
    clean = _codes(simulate_burst(**kwargs), sensor)
    assert np.count_nonzero(clean) <= 1e-4 * clean.size


def test_a_latent_scene_fitted_without_the_suspects_finds_hot_photosites_of_sharp_colour_planes():
    # raw12 RGGB dead leaves, bright: the search's predictions miss the edges an offset crosses on
    # these aliased planes; tested once more against the scene model fitted without the likeliest hot
    # photosites (solve.leftout): of the 137 offsets shown by 20+ standard errors the search finds 82 %
    # without that test, 92 % with it; 4 healthy photosites of the burst without defects flagged
    kwargs = dict(shape=(240, 320), n_frames=8, sensor=RAW12, scene="dead-leaves", exposure=0.75, seed=2)
    burst = simulate_burst(defects=0.005, **kwargs)
    hot = burst.defects == D.HOT
    plain = hot_offset_z(burst, RAW12, hot) > 20
    assert plain.sum() >= 100  # 137: enough for a share
    both = (_codes(burst, RAW12)[hot][plain] > 0).mean()
    clean = np.count_nonzero(_codes(simulate_burst(**kwargs), RAW12))
    search = (_codes(burst, RAW12, latent=False)[hot][plain] > 0).mean()  # input.defects_latent: false
    assert search <= 0.85 and both >= 0.9, (search, both)
    assert clean <= 1e-4 * burst.defects.size


def test_the_latent_scene_is_rendered_across_its_tiles_seams_as_in_one_tile_on_any_number_of_processes(monkeypatch):
    # a shaken burst (frames 10-20 px apart) whose colour plane is taller than a tile: near the seam a
    # reading falls outside one tile's scene in some frames, where that tile renders 0, not a value;
    # blended only where each tile sees the reading, the rendering is close to one tile's
    burst = simulate_burst(shape=(600, 160), n_frames=6, sensor=RAW12, scene="dead-leaves", seed=4,
                           shake=Shake(translation_px=12.0, rotation_deg=0.0))
    plane = np.ascontiguousarray(burst.frames[:, 0::2, 0::2].astype(np.float32) - RAW12.black_level)
    warp = GlobalWarp(burst.homographies).conjugate(plane_to_mosaic((0, 0)))
    out = np.zeros(plane.shape[1:], bool)
    out[::4, ::4] = True

    def rendered(workers=1):
        return leftout._rendered(plane, plane, warp, out, lambda t, frame: frame > 0, 0.5, None, workers)[0]

    tiled = rendered()
    np.testing.assert_array_equal(rendered(workers=2), tiled)  # its tiles fitted on two processes: the same
    monkeypatch.setattr(leftout, "SceneOptions", lambda **kw: SceneOptions(**{**kw, "tile": 1024}))
    whole = rendered()
    band = (slice(None), slice(230, 280))  # the plane's rows about the seam at 256
    both = (tiled[band] > 0) & (whole[band] > 0)
    assert both.mean() > 0.8  # (the rest out of view: the plane's sides)
    error = np.abs(tiled[band][both] / whole[band][both] - 1)
    # measured 1.3 / 4.8 % at the 90th / 99th percentile (6.9 / 50 % blended everywhere); away from
    # the seam 0.03 / 0.13 %: near a tile's edge its scene is fitted to fewer readings
    assert np.quantile(error, 0.9) < 0.03 and np.quantile(error, 0.99) < 0.1, np.quantile(error, [0.9, 0.99])


def test_the_scene_model_finds_the_plainly_shown_hot_photosites_the_search_misses(monkeypatch):
    # the 8-bit sensor's bright dead leaves, where the search's prediction of the scene (one or two
    # other readings) is as noisy as an offset: of the 42 offsets shown by 20 standard errors or more
    # the search finds 27 here, with the scene solver's offset test 40 (through the pipeline: motion
    # estimated, one frame held out; the `scene` solver forced); 1 healthy photosite flagged
    sensor = PRESETS["paper"]
    burst = simulate_burst(shape=(240, 320), n_frames=8, sensor=sensor, scene="dead-leaves", exposure=0.75, seed=2,
                           defects=0.005)
    frames = burst.frames.astype(np.float32) - sensor.black_level
    hot = burst.defects == D.HOT
    plain = hot_offset_z(burst, sensor, hot) > 20
    assert plain.sum() >= 30  # 42: enough for a share

    def found(**overrides):
        codes = _estimate(frames, sensor, **{"solver.method": "scene", **overrides}).defects[..., 0]
        return (codes[hot][plain] > 0).mean(), np.count_nonzero(codes[burst.defects == 0])

    with_model, healthy = found()
    monkeypatch.setattr(defective, "Z_MODEL_OFFSET", np.inf)
    search, _ = found()
    assert search <= 0.75 and with_model >= 0.9, (search, with_model)
    assert healthy <= 1e-4 * np.count_nonzero(burst.defects == 0) + 1


def test_the_scene_models_test_leaves_a_short_bursts_healthy_photosites_alone():
    # 5 frames, one held out: with 4 readings a photosite the latent scene takes up most of them;
    # scored so, 15 healthy photosites of this burst were coded hot (5-17 over seeds 3-6), now none
    sensor = PRESETS["paper"]
    burst = simulate_burst(shape=(240, 320), n_frames=5, sensor=sensor, scene="dead-leaves", seed=3)
    result = _estimate(burst.frames.astype(np.float32) - sensor.black_level, sensor, **{"solver.method": "scene"})
    assert result.report.defects.hot <= 1e-4 * burst.frames[0].size


def test_dead_and_stuck_photosites_in_a_black_region_are_found():
    # a dark 8-bit burst: where the scene is a few counts no ratio is measured; a stuck photosite reading
    # 200 there, or a dead one reading 0 where the scene gives 3, is found by the dim frames' tests. Of those
    # whose readings differ from a healthy one's with the scene known (response_z) by more than 10 / 40:
    # 112 of 114 / 49 of 50 flagged (104 / 44 without those tests; 111 / 49 with the dead photosites'
    # deficit over the dim frames alone and readings far above the scene asked only where fewer than
    # 4 frames are lit, which left one dead photosite lit in 2 of 8 frames unfound)
    sensor = PRESETS["paper"]
    kwargs = dict(shape=(240, 320), n_frames=8, sensor=sensor, scene="dead-leaves", exposure=0.075, seed=3)
    burst = simulate_burst(defects=0.005, **kwargs)
    odd = np.isin(burst.defects, [D.DEAD, D.STUCK])
    z = response_z(burst, sensor, odd)
    found = _codes(burst, sensor)[odd] > 0
    assert (z > 40).sum() >= 40 and (z > 10).sum() >= 100
    assert found[z > 40].mean() >= 0.95
    assert found[z > 10].mean() >= 0.98
    assert found[(z > 10) & (burst.defects[odd] == D.DEAD)].all()  # 58
    clean = _codes(simulate_burst(**kwargs), sensor)
    assert np.count_nonzero(clean) <= 1e-4 * clean.size


def _strokes(seed: int) -> np.ndarray:
    """A scene of thin bright strokes (1-3 px at the 480x640 it is drawn at) on black: a page of
    text, a night sky's trails."""
    import cv2

    rng = np.random.default_rng(seed)
    scene = np.zeros((480, 640), np.float32)
    for _ in range(120):
        start = rng.integers(0, (640, 480))
        end = start + rng.integers(-120, 120, 2)
        cv2.line(scene, tuple(map(int, start)), tuple(map(int, end)), float(rng.uniform(0.3, 1.0)),
                 int(rng.integers(1, 4)))
    return scene


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_thin_bright_strokes_on_black_are_not_defects(seed):
    # beside strokes finer than a colour plane samples, the median prediction errs by hundreds of DN
    # where the scene is black: such a photosite reads one value where both estimates of a healthy
    # one's variance say it would vary, and was flagged stuck (1127 / 807 / 1104 of these 19 200,
    # 4-6 %: over 5 % a plane is refused); the nearest readings do not confirm it (1 / 0 / 0 flagged)
    burst = simulate_burst(shape=(120, 160), n_frames=8, sensor=RAW12, scene=_strokes(seed), exposure=0.75,
                           seed=seed)
    assert np.median(burst.frames) == RAW12.black_level  # mostly black
    assert np.count_nonzero(_codes(burst, RAW12)) <= 2


@pytest.mark.parametrize("exposure", [0.2, 0.3])
def test_a_dark_smooth_scene_has_no_defects(exposure):
    # 8-bit readings of 2-3 counts: most of a photosite's readings are one count and its ratios'
    # median absolute deviation 0, so a response of 1.3 read as 6 standard errors out (5 + 0 + 6
    # and 0 + 0 + 4 flagged over the seeds); with the rounding's scatter counted, none
    y, x = np.mgrid[0:480, 0:640] / 480.0
    scene = (0.02 + 0.05 * np.exp(-((x - 0.7) ** 2 + (y - 0.5) ** 2) / 0.2)).astype(np.float32)
    sensor = PRESETS["paper"]
    for seed in range(3):
        burst = simulate_burst(shape=(120, 160), n_frames=8, sensor=sensor, scene=scene, exposure=exposure, seed=seed)
        assert np.median(burst.frames) <= 3
        assert not _codes(burst, sensor).any()


def test_stuck_photosites_are_found_in_frames_of_different_exposures():
    # a stuck photosite reads one value as read; divided by each frame's exposure it would not
    burst = simulate_burst(shape=(120, 160), n_frames=8, sensor=MONO, scene="dead-leaves", exposure=0.3,
                           exposure_jitter=0.1, defects=0.01, seed=5)
    frames = (burst.frames.astype(np.float32) - MONO.black_level)[..., None]
    codes = defective.find(frames, None, ("Y",), excluded=None, exposures=burst.exposures,
                           warp=GlobalWarp(burst.homographies), saturation=burst.saturation).codes[..., 0]
    stuck = burst.defects == D.STUCK
    assert np.ptp(burst.exposures) > 0.1 and stuck.sum() >= 20
    # every one flagged, 27 of 29 as stuck (2 stuck near black read as dead), as without the jitter
    assert (codes[stuck] > 0).all() and (codes[stuck] == D.STUCK).mean() >= 0.9


@pytest.mark.parametrize("sensor", [MONO, RAW12])
def test_strips_of_rows_change_nothing(monkeypatch, sensor):
    # the per-photosite statistics run a strip of rows at a time (memory): any strip height, the same
    # codes (here 7 rows of the 6 frames, and 1 row for the offset fit's quarter strips)
    burst = simulate_burst(shape=(120, 160), n_frames=6, sensor=sensor, scene="dead-leaves", exposure=0.15,
                           defects=0.01, seed=3)
    whole = _codes(burst, sensor)
    monkeypatch.setattr(stacks, "STRIP_READINGS", 7 * 6 * 160)
    assert np.count_nonzero(whole) > 100 and np.array_equal(_codes(burst, sensor), whole)


@pytest.mark.parametrize("sensor", [MONO, RAW12])
def test_threads_change_nothing(monkeypatch, sensor):
    # the statistics along the frames and the nearest readings run a strip of rows a thread: on any
    # number of threads, the same codes and noise (here several strips a thread, frames of different
    # exposures)
    burst = simulate_burst(shape=(120, 160), n_frames=6, sensor=sensor, scene="dead-leaves", exposure=0.15,
                           exposure_jitter=0.1, defects=0.01, seed=3)
    frames = (burst.frames.astype(np.float32) - sensor.black_level)[..., None]
    monkeypatch.setattr(stacks, "STRIP_READINGS", 7 * 6 * 160)
    found = [defective.find(frames, sensor.cfa, ("Y",), excluded=None, exposures=burst.exposures,
                            warp=GlobalWarp(burst.homographies), saturation=burst.saturation, threads=threads)
             for threads in (1, 2, 3)]
    assert np.count_nonzero(found[0].codes) > 100
    for other in found[1:]:
        np.testing.assert_array_equal(other.codes, found[0].codes)
        assert other.noise == found[0].noise


def test_each_strip_keeps_the_order_on_threads():
    shape = (4, 1000, 50)
    expected = [(rows.start, rows.stop) for rows in stacks.strips(shape, parts=2 ** 20 // 200)]
    got = stacks.each_strip(lambda rows: (rows.start, rows.stop), shape, parts=2 ** 20 // 400, threads=2)
    assert got == expected and len(got) > 10


@pytest.mark.parametrize("kind", ["weak", "stuck"])
def test_a_response_below_half_the_planes_is_a_defect(kind):
    # a photosite giving 0.25-0.4 of its scene: a gain the default range (k at most 2) does not hold.
    # Weak (its readings follow the scene): dead, but for one of the 40 whose trajectory crosses an
    # edge (9 -> 80 DN); stuck at that share of its first reading in every frame: stuck, or dead
    # where 8-bit noise cannot tell it from constant. With 0.25 as the bound: 1 of 40 weak ones and
    # 35 of 40 stuck flagged
    sensor = PRESETS["paper"]
    kwargs = dict(shape=(120, 160), n_frames=8, sensor=sensor, scene="procedural", exposure=0.75, seed=4)
    burst = simulate_burst(**kwargs)
    rng = np.random.default_rng(0)
    odd = np.zeros(burst.frames.shape[1:], bool)
    odd[rng.integers(8, 112, 40), rng.integers(8, 152, 40)] = True
    share = rng.uniform(0.25, 0.4, odd.sum())
    frames = burst.frames.astype(np.float64)
    frames[:, odd] = np.round(share * (frames[:, odd] if kind == "weak" else frames[:1, odd]))
    codes = _codes(dataclasses.replace(burst, frames=frames.astype(burst.frames.dtype)), sensor)
    assert (codes[odd] > 0).sum() >= (39 if kind == "weak" else 40)
    if kind == "weak":
        assert (codes[odd] == D.DEAD).sum() >= 39
    assert np.count_nonzero(codes[~odd]) == 0


def test_one_value_chance_is_that_of_rounded_normal_readings():
    rng = np.random.default_rng(0)
    for sigma, n_frames in ((1.0, 4), (0.7, 6)):
        seen = [(np.ptp(np.round(mean + rng.normal(0.0, sigma, (400_000, n_frames))), axis=1) == 0).mean()
                for mean in (0.0, 0.5)]
        chance = one_value_chance(sigma, n_frames)
        assert abs(chance - max(seen)) < 4 * np.sqrt(chance / 400_000)


def test_more_frames_ask_less_spread_of_a_stuck_photosite():
    # a healthy photosite reading one value in every frame by no more chance than at 3 steps and 8 frames
    assert quantised_steps(5) == quantised_steps(8) == QUANTISED_STEPS
    steps = [quantised_steps(n) for n in (9, 12, 16, 32, 1000)]
    assert steps == sorted(steps, reverse=True) and steps[0] < QUANTISED_STEPS and steps[2] < 1.1 and steps[-1] > 0
    assert np.isclose(one_value_chance(steps[2], 16), ONE_VALUE_CHANCE, rtol=1e-3)
    # 16 frames of a bright 8-bit burst: 56 of 57 stuck photosites found (52 at 3 steps), none healthy
    kwargs = dict(shape=(240, 320), n_frames=16, sensor=PRESETS["paper"], scene="dead-leaves", exposure=0.75, seed=2)
    burst = simulate_burst(defects=0.005, **kwargs)
    assert (_codes(burst, PRESETS["paper"])[burst.defects == D.STUCK] > 0).sum() >= 56
    assert not _codes(simulate_burst(**kwargs), PRESETS["paper"]).any()


def test_too_few_frames_find_nothing():
    burst = simulate_burst(shape=(64, 80), n_frames=D.MIN_FRAMES - 1, defects=0.01, seed=1)
    assert not _codes(burst, PRESETS["paper"]).any()


def test_a_dark_frame_marks_hot_photosites_of_every_offset():
    rng = np.random.default_rng(0)
    dark = rng.normal(0.0, 2.0, (4, 120, 160, 1)).mean(axis=0)  # a master dark: 4 averaged, 1 DN noise
    hot = np.zeros(dark.shape, bool)
    hot.flat[rng.choice(dark.size, 200, replace=False)] = True
    dark[hot] += 5.5 * 2.0  # 5.5 sigmas of a single dark frame's noise (a lit frame's is larger)
    found = defective.hot_in_dark(dark, "RGGB", ("Y",))
    assert found[hot].all() and not found[~hot].any()


def test_repair_fills_a_defect_from_its_own_colour():
    mosaic = np.tile(np.array([[10.0, 20.0], [30.0, 40.0]], np.float32), (8, 8))[..., None]
    broken = mosaic.copy()
    codes = np.zeros(mosaic.shape, np.uint8)
    for y, x in ((4, 4), (4, 5), (0, 0), (15, 15)):  # one of each colour, corners included
        broken[y, x] = np.inf if x % 2 else 0.0
        codes[y, x] = D.STUCK
    np.testing.assert_array_equal(defective.repair(broken, codes, "RGGB", ("Y",)), mosaic)
    assert defective.repair(broken, np.zeros_like(codes), "RGGB", ("Y",)) is broken


def _estimate(frames, sensor, **overrides):
    return api.estimate(frames, cfa=sensor.cfa, saturation=sensor.white_level - sensor.black_level,
                        **{"solver.workers": 1, **overrides})


def test_an_estimate_leaves_defects_out_writes_them_and_repairs_the_corrected_frames(tmp_path):
    # a sensor's 0.14 % of defects (0.1 % hot, 0.02 % dead, 0.02 % stuck)
    kwargs = dict(shape=(128, 160), n_frames=7, sensor=MONO, scene="dead-leaves", exposure=0.3, seed=4)
    burst = simulate_burst(defects=0.0014, **kwargs)
    frames = burst.frames.astype(np.float32) - MONO.black_level
    result = _estimate(frames, MONO)
    codes = result.defects[..., 0]
    truth = burst.defects
    assert (codes[(truth == D.DEAD) | (truth == D.STUCK)] > 0).all()
    assert np.count_nonzero(codes[truth == 0]) <= 1e-4 * np.count_nonzero(truth == 0)
    assert (result.k[codes > 0] == 1).all() and (result.confidence[codes > 0] == 0).all()
    counts = result.report.defects
    assert (counts.hot, counts.dead, counts.stuck) == tuple(int((codes == c).sum()) for c in (D.HOT, D.DEAD, D.STUCK))
    assert result.report.to_json()["defects"]["total"] == counts.total > 0

    # the healthy photosites' gains are as good as on the same burst without defects (measured 0.917 %
    # and 0.929 %; at 1 % of defects 0.929 %, 0.917 % against 0.811 % on seed 5: the repaired readings
    # are smoother than the scene)
    clean = _estimate(simulate_burst(**kwargs).frames.astype(np.float32) - MONO.black_level, MONO)
    healthy = (truth == 0) & (result.confidence[..., 0] > 0) & (clean.confidence[..., 0] > 0)

    def residual(k):
        corrected = k[..., 0][healthy] * burst.gain[healthy]
        return np.std(corrected / corrected.mean())
    assert residual(result.k) <= 1.05 * residual(clean.k)

    result.write(tmp_path / "est")
    planes, _ = read_exr_planes(tmp_path / "est" / "gain_map.exr")
    np.testing.assert_array_equal(planes["defect"], codes)
    corrected = read_exr_planes(tmp_path / "est" / "corrected" / "frame_000.exr")[0]["Y"]
    expected = defective.repair(frames[0, ..., None] * result.k, result.defects, None, ("Y",))[..., 0]
    np.testing.assert_array_equal(corrected, expected)
    stuck = np.argwhere(codes == D.STUCK)[0]
    assert corrected[tuple(stuck)] != frames[0][tuple(stuck)] * result.k[tuple(stuck)][0]

    # apply repairs from the stored map (and leaves the defects as they are with repair=False)
    (tmp_path / "in").mkdir()
    for i, frame in enumerate(frames[:2]):
        write_exr(tmp_path / "in" / f"f{i}.exr", {"Y": frame})
    gain_map = tmp_path / "est" / "gain_map.exr"
    api.apply(tmp_path / "in", gain_map=gain_map, out_dir=tmp_path / "applied")
    np.testing.assert_array_equal(read_exr_planes(tmp_path / "applied" / "f0.exr")[0]["Y"], corrected)
    api.apply(tmp_path / "in", gain_map=gain_map, out_dir=tmp_path / "raw", repair=False)
    plain = read_exr_planes(tmp_path / "raw" / "f0.exr")[0]["Y"]
    np.testing.assert_array_equal(plain, frames[0] * result.k[..., 0])


def test_defects_off_looks_for_none():
    burst = simulate_burst(shape=(96, 128), n_frames=6, sensor=MONO, defects=0.01, seed=4)
    result = _estimate(burst.frames.astype(np.float32) - MONO.black_level, MONO, **{"input.defects": False})
    assert result.defects is None and result.report.defects is None
    assert result.report.to_json()["defects"] is None


@pytest.mark.parametrize("size", ["192x160", pytest.param("256x192", marks=pytest.mark.slow)])
def test_a_raw_burst_reports_its_defects_and_the_map_holds_them(tmp_path, size):
    import json

    from helpers import run_cli

    sim, est = tmp_path / "sim", tmp_path / "est"
    run_cli("simulate", sim, "--preset", "raw12", "--format", "dng", "--size", size, "--frames", "7",
            "--scene", "dead-leaves", "--exposure", "0.3", "--defects", "0.005", "--seed", "3")
    record = json.loads(run_cli("estimate", sim, "-o", est, "--json", "--workers", "2").stdout)
    truth = read_exr_planes(sim / "truth" / "defects.exr")[0]["defect"]
    codes = read_exr_planes(est / "gain_map.exr")[0]["defect"]
    assert (codes[(truth == D.DEAD) | (truth == D.STUCK)] > 0).all()
    # with estimated motion: 1 of 48 906 healthy photosites flagged (hot), 0.2e-4; at 192x160 1 of 30 566
    assert np.count_nonzero(codes[truth == 0]) <= 1e-4 * np.count_nonzero(truth == 0)
    assert record["defects"]["total"] == np.count_nonzero(codes) > 0
    assert json.loads((est / "report.json").read_text())["defects"] == record["defects"]


def test_a_dark_frame_marks_the_hot_photosites_the_burst_cannot_tell(tmp_path):
    burst = simulate_burst(shape=(128, 160), n_frames=6, sensor=MONO, scene="dead-leaves", exposure=0.3, seed=6)
    rng = np.random.default_rng(6)
    dark = rng.normal(0.0, 1.0, (128, 160)).astype(np.float32)
    hot = np.zeros(dark.shape, bool)
    hot.flat[rng.choice(dark.size, 20, replace=False)] = True
    dark[hot] += 8.0  # 8 DN: a small offset against a lit photosite's ~35 DN of noise at 30 % exposure
    (tmp_path / "in").mkdir()
    for i, frame in enumerate(burst.frames.astype(np.float32) - MONO.black_level):
        write_exr(tmp_path / "in" / f"f{i}.exr", {"Y": frame + dark})
    write_exr(tmp_path / "dark.exr", {"Y": dark})
    result = api.estimate(tmp_path / "in", **{"solver.workers": 1, "input.dark": str(tmp_path / "dark.exr")})
    assert (result.defects[..., 0][hot] == D.HOT).all()
    assert result.report.defects.dark_frame and result.report.defects.hot >= 20
    without = api.estimate(tmp_path / "in", **{"solver.workers": 1})
    assert not (without.defects[..., 0][hot] > 0).any()  # the offsets are small beside the gain spread


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(1, 9), st.integers(1, 4), st.integers(1, 5)),
              elements=st.one_of(st.floats(-1e6, 1e6, width=32), st.just(np.nan))))
def test_nan_median_is_numpys(stack):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
        expected = np.nanmedian(stack, axis=0)
    got = stacks.nan_median(stack)
    assert got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)


def test_nan_median_on_threads_is_the_same(monkeypatch):
    monkeypatch.setattr(stacks, "STRIP_READINGS", 5 * 7 * 30)  # 7 rows a strip, 3 a thread's
    stack = np.random.default_rng(1).normal(size=(5, 100, 30)).astype(np.float32)
    stack[stack > 1.5] = np.nan
    np.testing.assert_array_equal(stacks.nan_median(stack, threads=2), stacks.nan_median(stack))
