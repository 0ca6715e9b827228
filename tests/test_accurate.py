import numpy as np
import pytest

from gainfpn_cli import metrics
from gainfpn_cli.errors import EstimationError
from gainfpn_cli.geometry.resample import low_pass
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.parallel import single_threaded_math
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.accurate import (
    AccurateOptions,
    solve_accurate,
    solve_accurate_many,
)
from gainfpn_cli.solve.result import sigma_from_confidence

NOISELESS = with_overrides(PRESETS["paper"], read_noise_e=0.0, shot_noise=False, adc_bits=16)


def _flat(shape=(60, 80), n_frames=6, seed=1, shake=Shake(translation_px=1.0, rotation_deg=0.1)):
    burst = simulate_burst(shape=shape, n_frames=n_frames, seed=seed, sensor=NOISELESS,
                           scene=np.full((8, 8), 0.5, np.float32), shake=shake)
    return burst, burst.ideal * burst.gain


def _scores(result, burst, frames, margin=8):
    mask = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], margin)
    ratio = metrics.mse(frames[0], burst.ideal[0], mask) / metrics.mse(result.k * frames[0], burst.ideal[0], mask)
    return ratio, metrics.residual_fpn_percent(result.k, burst.gain, mask)


def test_flat_noise_free_scene_gives_the_gauged_truth():
    # On a flat scene the interpolated corrected frame is exact, so k = 1/a
    # solves (*) exactly; the gauge then divides by the low band. The oracle
    # is (1/a) / LP(1/a). What is left is the low-band penalty's pull near
    # the gauge cut-off: measured 0.12 % median, so 0.3 % is the bound.
    burst, frames = _flat()
    result = solve_accurate(frames, burst.homographies, workers=1)
    est = result.confidence > 0
    assert est.mean() > 0.9
    inverse = 1.0 / burst.gain.astype(np.float64)
    oracle = inverse / low_pass(inverse, 8.0, est)
    oracle /= oracle[est].mean()
    assert np.median(np.abs(result.k / oracle - 1)[est]) < 0.003
    # white 5 % FPN minus its Gaussian(8 px) low band leaves 5 % / (sqrt(4 pi) 8) = 0.18 %
    assert metrics.residual_fpn_percent(result.k, burst.gain, est) < 0.5


def test_constant_gain_gives_constant_k():
    # a band-limited textured scene (features >= 3 px), no FPN, no noise:
    # Lanczos-4 interpolation is nearly exact there, so k must be 1. (Next to
    # edges sharper than a pixel no kernel is exact; see the confidence test.)
    import cv2

    rng = np.random.default_rng(0)
    # about 1.2 scene px per raster px and 2 raster px per sensor px: sigma 4 -> ~2.4 sensor px
    scene = cv2.GaussianBlur(rng.uniform(0.2, 0.8, (100, 125)).astype(np.float32), (0, 0), 4.0)
    scene = (scene - scene.min()) / (scene.max() - scene.min()) * 0.8 + 0.1
    burst = simulate_burst(shape=(40, 50), n_frames=4, seed=2, scene=scene, sensor=with_overrides(NOISELESS, fpn_pixel=0.0))
    result = solve_accurate(burst.ideal, burst.homographies, workers=1)
    est = result.confidence > 0
    # OpenCV quantises sample positions to 1/32 px: a sample errs by up to
    # |grad i| / 64, i.e. a relative error of |grad i| / i / 64 per comparison
    gy, gx = np.gradient(burst.ideal[0].astype(np.float64))
    relative = np.hypot(gx, gy) / burst.ideal[0] / 64
    deviation = np.abs(result.k - 1)[est]
    assert np.median(deviation) <= np.median(relative)
    assert deviation.max() <= relative.max()


def test_confidence_is_lower_where_interpolation_cannot_follow():
    # the procedural scene has shapes with half-pixel edges of up to 12:1
    # contrast: aliased, so k errs next to them; confidence must say so
    burst = simulate_burst(shape=(40, 50), n_frames=4, seed=2, sensor=with_overrides(NOISELESS, fpn_pixel=0.0))
    result = solve_accurate(burst.ideal, burst.homographies, workers=1)
    est = result.confidence > 0
    wrong = est & (np.abs(result.k - 1) > 0.05)
    right = est & (np.abs(result.k - 1) < 0.005)
    assert wrong.any() and right.any()
    assert np.median(result.confidence[wrong]) < np.median(result.confidence[right]) - 0.1


@pytest.mark.parametrize("n_frames", [3, 4, 5])
def test_sigma_k_counts_what_the_fit_takes_of_the_residuals(n_frames):
    # a dark procedural burst (7.5 % exposure), true motion: k's error is the noise's. The fit takes
    # 1 / T of each pixel's residuals into k and 1 / T into the scene its partners give, so the raw
    # residuals say (T - 2) / T of the noise and k keeps (T - 1) / T of each reading's information:
    # without that, k erred 2.1x, 1.7x and 1.5x its sigma_k at 3, 4 and 5 frames (240x320). Measured
    # here (120x160, seed 1), median over the tenths of sigma_k: 1.11, 1.04, 1.03
    burst = simulate_burst(shape=(120, 160), n_frames=n_frames, seed=1, exposure=0.075)
    frames = burst.frames.astype(np.float32) - burst.sensor.black_level
    result = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1)
    use = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], 16)
    tenths = metrics.confidence_deciles(result.k, burst.gain, sigma_from_confidence(result.confidence), use)
    assert 0.9 <= np.median(tenths) <= 1.2, tenths


def test_headline_accuracy_on_the_papers_sensor():
    # issue 3: accurate mode >= 12x MSE reduction and <= 1.2 % residual gain
    # FPN on 8-frame bursts of the paper's sensor with true motion. Measured
    # 19-24x and 0.52-0.64 % on 120x160 bursts (noise floor ~1.1 DN^2 of ~32).
    for seed in (1, 2):
        burst = simulate_burst(shape=(96, 128), n_frames=8, seed=seed)
        frames = burst.frames.astype(np.float32)
        ratio, residual = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1),
                                  burst, frames)
        assert ratio >= 12 and residual <= 1.2, (seed, ratio, residual)


def test_headline_accuracy_on_dead_leaves():
    # the same targets on the photograph-like dead-leaves scene (sharp
    # occluding edges at every scale, where interpolation errs most). Measured
    # on 10 bursts of 96x128: 12.0-17.3x, 0.69-1.06 %; the median of three
    # bursts must meet the target (their values: 17.3, 12.9, 14.4x).
    scores = []
    for seed in range(3):
        burst = simulate_burst(shape=(96, 128), n_frames=8, seed=seed, scene="dead-leaves")
        frames = burst.frames.astype(np.float32)
        scores.append(_scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1),
                              burst, frames))
    ratio, residual = np.median(scores, axis=0)
    assert ratio >= 12 and residual <= 1.2, scores


@pytest.mark.xfail(strict=True, reason="issue 3 gap: on dead leaves, 3 % pixel + 4 % column FPN gives 6.2-12.1x "
                   "over 10 bursts (median 8.5); seeds 3 and 9 miss 8x at 7.5x and 6.2x, with the columns' "
                   "means off by 0.9 % and a 1.7 % high-band error")
@pytest.mark.parametrize("seed", [3, 9])
def test_pixel_and_column_fpn_on_dead_leaves(seed):
    sensor = with_overrides(PRESETS["paper"], fpn_pixel=0.03, fpn_column=0.04)
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=seed, sensor=sensor, scene="dead-leaves")
    frames = burst.frames.astype(np.float32)
    ratio, _ = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1), burst, frames)
    assert ratio >= 8


def test_pixel_and_column_fpn():
    # issue 3: 3 % pixel + 4 % column FPN, accurate mode >= 8x (measured 10-13x)
    sensor = with_overrides(PRESETS["paper"], fpn_pixel=0.03, fpn_column=0.04)
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=1, sensor=sensor)
    frames = burst.frames.astype(np.float32)
    ratio, _ = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1), burst, frames)
    assert ratio >= 8


def test_anchoring_every_frame_beats_anchoring_the_reference():
    # the reference-only form copies frame 0's temporal noise into k
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=3)
    frames = burst.frames.astype(np.float32)
    every = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1), burst, frames)
    ref = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1,
                                 options=AccurateOptions(anchors="reference")), burst, frames)
    assert every[1] < ref[1]


def test_tiles_are_seamless_and_worker_count_changes_no_bit():
    burst = simulate_burst(shape=(80, 100), n_frames=6, seed=4)
    frames = burst.frames.astype(np.float32)
    tiled = AccurateOptions(tile=40, halo=16)
    one = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1, options=tiled)
    two = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=2, options=tiled)
    np.testing.assert_array_equal(one.k, two.k)
    np.testing.assert_array_equal(one.confidence, two.confidence)
    assert one.stats.tiles == 6  # 2 rows x 3 columns of 40 px cores
    # a seam is a larger error along the tiles' borders than inside them
    est = (one.confidence > 0) & metrics.interior_mask(frames.shape[1:], 8)
    error = one.k * burst.gain
    error = error / np.median(error[est]) - 1
    near = np.zeros(est.shape, bool)
    near[37:43, :] = True
    for x in (40, 80):
        near[:, x - 3 : x + 3] = True
    rms = lambda m: np.sqrt(np.mean(error[m] ** 2))  # noqa: E731
    assert rms(est & near) < 1.3 * rms(est & ~near)


def test_zero_motion_is_an_error():
    burst, frames = _flat(shake=Shake(translation_px=0.0, rotation_deg=0.0))
    with pytest.raises(EstimationError, match="no motion"):
        solve_accurate(frames, burst.homographies, workers=1)


def test_clipped_region_is_not_estimated():
    burst = simulate_burst(shape=(48, 64), n_frames=5, seed=5)
    frames = burst.frames.astype(np.float32)
    frames[:, :, :12] = burst.saturation
    result = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1)
    assert np.all(result.confidence[:, :10] == 0) and np.all(result.k[:, :10] == 1.0)
    assert np.all(np.isfinite(result.k)) and result.k[result.confidence > 0].mean() == pytest.approx(1.0, abs=1e-6)


def test_nothing_comparable_is_an_error():
    burst, frames = _flat()
    with pytest.raises(EstimationError, match="no pixel could be compared"):
        solve_accurate(np.zeros_like(frames), burst.homographies, workers=1)


@pytest.mark.parametrize("kernel", ["bilinear", "cubic", "lanczos4"])
def test_every_kernel_runs_and_helps(kernel):
    burst = simulate_burst(shape=(64, 80), n_frames=6, seed=6)
    frames = burst.frames.astype(np.float32)
    result = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1,
                            options=AccurateOptions(kernel=kernel))
    ratio, _ = _scores(result, burst, frames)
    assert ratio > 4
    assert 0 <= result.confidence.min() and result.confidence.max() <= 1


def test_validates():
    with pytest.raises(ValueError, match="frames must have shape"):
        solve_accurate(np.zeros((1, 8, 8)), np.eye(3)[None])
    with pytest.raises(ValueError, match="motion is given for 1 frames, there are 2"):
        solve_accurate(np.zeros((2, 8, 8)), np.eye(3)[None])
    with pytest.raises(ValueError, match="homographies must be finite"):
        solve_accurate(np.zeros((2, 8, 8)), np.full((2, 3, 3), np.nan))
    with pytest.raises(ValueError, match="kernel must be"):
        solve_accurate(np.zeros((2, 8, 8)), np.stack([np.eye(3)] * 2), options=AccurateOptions(kernel="sinc"))


def test_gains_outside_the_physical_range_are_not_emitted():
    burst = simulate_burst(shape=(48, 64), n_frames=5, seed=8)
    frames = burst.frames.astype(np.float32)
    narrow = AccurateOptions(gain_range=(0.99, 1.01))  # narrower than the 5 % FPN
    result = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1, options=narrow)
    est = result.confidence > 0
    assert result.stats.out_of_range_pixels > 0
    assert np.all(result.k[~est] == 1.0)
    assert np.all((result.k >= 0.98) & (result.k <= 1.02))  # the final mean-1 rescale moves the range a little


@pytest.mark.parametrize("shape", [(8, 8), (5, 40)])
def test_tiny_frames(shape):
    # flat scene seen by 5 % FPN pixels; every frame is s * a whatever the motion
    a = 1 + 0.05 * np.random.default_rng(0).standard_normal(shape)
    frames = np.stack([100.0 * a] * 4).astype(np.float32)
    H = np.stack([np.eye(3)] + [np.array([[1, 0, 0.3 * t], [0, 1, 0.2 * t], [0, 0, 1.0]]) for t in range(1, 4)])
    with pytest.raises(EstimationError, match=r"too small for the lanczos4 kernel.*bilinear"):
        solve_accurate(frames, H, workers=1)
    result = solve_accurate(frames, H, workers=1, options=AccurateOptions(kernel="bilinear"))
    assert np.all(np.isfinite(result.k)) and (result.confidence > 0).any()


def test_partner_frames_are_the_nearest_in_burst_order():
    from gainfpn_cli.solve.accurate import partner_frames

    assert partner_frames(0, 8, 2) == [1, 7]
    assert partner_frames(3, 8, 3) == [4, 2, 5]
    assert partner_frames(1, 3, 0) == [2, 0] and partner_frames(1, 3, 5) == [2, 0]
    assert sorted(partner_frames(5, 8, 0)) == [0, 1, 2, 3, 4, 6, 7]


def test_fewer_partners_cost_little_accuracy():
    # measured on 480x640: 2 partners 19.1x, all 7 partners 20.4x, half the time
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=1)
    frames = burst.frames.astype(np.float32)
    every, _ = _scores(solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1), burst, frames)
    two = solve_accurate(frames, burst.homographies, saturation=burst.saturation, workers=1,
                         options=AccurateOptions(partners=2))
    ratio, _ = _scores(two, burst, frames)
    assert 0.8 * every <= ratio <= 1.05 * every


def test_the_greens_on_their_lattice_alias_less_than_each_green_plane():
    # measured with the true motion, 160x200 raw12 dead leaves (seed 4):
    # residual 1.10 % together, 2.01 % and 1.83 % alone
    from gainfpn_cli.geometry.cfa import green_lattice, plane_to_mosaic
    from gainfpn_cli.geometry.warps import GlobalWarp
    from gainfpn_cli.metrics import residual_fpn_percent
    from gainfpn_cli.sim.sensor import PRESETS

    sensor = PRESETS["raw12"]
    burst = simulate_burst(shape=(160, 200), n_frames=8, sensor=sensor, scene="dead-leaves", seed=4)
    frames = burst.frames.astype(np.float32) - sensor.black_level
    motion = GlobalWarp(burst.homographies)
    alone = []
    for dy, dx in ((0, 1), (1, 0)):
        result = solve_accurate(frames[:, dy::2, dx::2], motion.conjugate(plane_to_mosaic((dy, dx))),
                                saturation=burst.saturation, workers=1)
        alone.append(residual_fpn_percent(result.k, burst.gain[dy::2, dx::2], result.confidence > 0))
    lattice = green_lattice("RGGB", frames.shape[1:])
    result = solve_accurate(lattice.gather(frames), motion.conjugate(lattice.S), saturation=burst.saturation, workers=1)
    est = result.confidence[lattice.v, lattice.u] > 0
    together = residual_fpn_percent(result.k[lattice.v, lattice.u], burst.gain[lattice.rows, lattice.cols], est)
    assert est.mean() > 0.9
    assert together < 0.75 * min(alone), (together, alone)


def test_a_poorly_determined_solve_stops_early_and_gains_by_it():
    # 4 frames of 240x320, true motion: GMRES needs 500 iterations a round to
    # converge here, and the converged k is worse (2.52 % residual) than the
    # one after 50 (2.18 %): the iterations past that fit noise into the
    # modes few comparisons pin down. The default stops at 50 a round.
    burst = simulate_burst(shape=(240, 320), n_frames=4, seed=2, scene="dead-leaves")
    frames = burst.frames.astype(np.float32) - burst.sensor.black_level
    result = solve_accurate(frames, burst.homographies, workers=1,
                            options=AccurateOptions(kernel="cubic", partners=3, robust_rounds=1))
    assert result.stats.gmres_iterations == (100,)
    assert metrics.residual_fpn_percent(result.k, burst.gain, result.confidence > 0) < 2.3


def test_sample_phase_is_zero_on_pixels_and_two_between_four():
    from gainfpn_cli.solve.phase import sample_phase

    shift = lambda dx, dy: np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])  # noqa: E731
    np.testing.assert_allclose(sample_phase(shift(3.0, -2.0), (4, 5)), 0.0, atol=1e-6)
    np.testing.assert_allclose(sample_phase(shift(0.5, 0.5), (4, 5)), 2.0, atol=1e-6)
    np.testing.assert_allclose(sample_phase(shift(0.5, 1.0), (4, 5)), 1.0, atol=1e-6)
    np.testing.assert_allclose(sample_phase(shift(0.25, 0.0), (4, 5)), 0.5, atol=1e-6)


def test_phase_weights_recover_the_precision_of_each_comparison():
    # residuals drawn with variance a + b phase (a: noise, b: interpolation
    # error, larger on the right half); the weights are u / (a + b phase)
    from gainfpn_cli.solve.phase import phase_weighted, sample_phase

    rng = np.random.default_rng(5)
    shape = (64, 64)
    a, b = 4.0, np.where(np.arange(64) < 32, 10.0, 40.0)[None, :] * np.ones(shape)
    pair_maps = [(0, 1, np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]]))
                 for dx, dy in rng.uniform(-3, 3, (40, 2))]
    valid = [np.ones(shape, bool)] * len(pair_maps)
    residuals = [np.sqrt(a + b * sample_phase(M, shape)) * rng.standard_normal(shape) for _, _, M in pair_maps]
    weights = phase_weighted([np.ones(shape) for _ in pair_maps], residuals, valid, pair_maps, shape)
    # w (a + b phase) is the same constant u ~ a for every comparison, on both halves
    scaled = np.stack([w * (a + b * sample_phase(M, shape)) for w, (_, _, M) in zip(weights, pair_maps)])
    for half in (slice(8, 24), slice(40, 56)):  # away from the seam and the border
        core = scaled[:, 8:-8, half]
        assert np.median(core) == pytest.approx(a, rel=0.15)
        assert np.percentile(core, 95) / np.percentile(core, 5) < 2.0  # a 9x9 window's fit, not exact
    flat = phase_weighted([np.ones(shape) for _ in pair_maps], [np.sqrt(a) * rng.standard_normal(shape)
                                                               for _ in pair_maps], valid, pair_maps, shape)
    assert np.percentile(np.stack(flat), 5) > 0.6  # no interpolation error: every comparison keeps ~ its weight


def test_phase_weights_help_where_the_planes_alias():
    # a RAW mosaic's colour planes sample the scene every 2 photosites: their
    # interpolation errs most between pixels. Here (red plane, true motion)
    # measured 2.31 -> 2.01 % (seeds 5 and 6: 2.49 -> 2.05, 1.63 -> 1.46 %).
    from gainfpn_cli.geometry.cfa import plane_to_mosaic
    from gainfpn_cli.geometry.warps import GlobalWarp
    from gainfpn_cli.metrics import residual_fpn_percent
    from gainfpn_cli.sim.sensor import PRESETS

    sensor = PRESETS["raw12"]
    burst = simulate_burst(shape=(160, 200), n_frames=8, sensor=sensor, scene="dead-leaves", seed=4)
    frames = (burst.frames.astype(np.float32) - sensor.black_level)[:, 0::2, 0::2]  # the red plane
    motion = GlobalWarp(burst.homographies).conjugate(plane_to_mosaic((0, 0)))
    residual = {}
    for on in (False, True):
        result = solve_accurate(frames, motion, saturation=burst.saturation, workers=1,
                                options=AccurateOptions(phase_weights=on))
        residual[on] = residual_fpn_percent(result.k, burst.gain[0::2, 0::2], result.confidence > 0)
    assert residual[True] < 0.9 * residual[False], residual


def test_problems_solved_together_are_solved_as_one_at_a_time():
    # the halves of the frames (solving.solve_raws) share one pool: the same k, bit for bit
    burst = simulate_burst(shape=(96, 128), n_frames=8, seed=2)
    frames = burst.frames.astype(np.float32)
    problems = [dict(frames=frames[idx], motion=GlobalWarp(burst.homographies[idx]), saturation=burst.saturation)
                for idx in ([0, 2, 4, 6], [1, 3, 5, 7])]
    together = solve_accurate_many(problems, workers=2)
    for problem, result in zip(problems, together):
        with single_threaded_math():  # as in the workers (and as pipeline.estimate runs it)
            alone = solve_accurate(problem["frames"], problem["motion"], saturation=burst.saturation, workers=1)
        np.testing.assert_array_equal(result.k, alone.k)
        np.testing.assert_array_equal(result.confidence, alone.confidence)
