import dataclasses
import json

import numpy as np
import pytest

from gainfpn_cli import files as io
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.scenes import dead_leaves, procedural_scene
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import render, simulate_burst
from gainfpn_cli.sim.truth import load_truth, save_burst

PAPER = PRESETS["paper"]
STILL = Shake(translation_px=0.0, rotation_deg=0.0)


def test_paper_preset_is_the_papers_sensor():
    assert (PAPER.conversion_gain_uv, PAPER.swing_v, PAPER.read_noise_e, PAPER.adc_bits, PAPER.fpn_pixel) == (
        32.5, 1.0, 50.0, 8, 0.05)
    assert PAPER.full_well_e == pytest.approx(30769.23, rel=1e-6)


def test_no_fpn_no_noise_gives_the_ideal_frames():
    # every noise off: frames are the ideal frames rounded by the ADC, exactly
    sensor = with_overrides(PAPER, fpn_pixel=0.0, read_noise_e=0.0, shot_noise=False, black_level=3)
    burst = simulate_burst(shape=(40, 56), n_frames=3, sensor=sensor, seed=5)
    assert np.all(burst.gain == 1.0)
    np.testing.assert_array_equal(burst.frames, np.floor(burst.ideal.astype(np.float64) + 0.5) + 3)


def test_gain_spread_matches_sigma():
    sensor = with_overrides(PAPER, fpn_pixel=0.03, fpn_column=0.04, fpn_row=0.02)
    burst = simulate_burst(shape=(200, 400), n_frames=1, sensor=sensor, seed=9)
    a = burst.gain.astype(np.float64)
    column = a.mean(axis=0)
    # column means hold the column gain plus pixel noise averaged over 200 rows
    pixel_in_col = 0.03 / np.sqrt(200)
    col_sigma = np.sqrt(max(column.var(ddof=1) - pixel_in_col**2, 0))
    # sample sigma of n Gaussian values has relative error 1/sqrt(2n): allow 4 of those
    assert col_sigma == pytest.approx(0.04, rel=4 / np.sqrt(2 * 400))
    residual = a / column[None, :]
    row_means = residual.mean(axis=1)
    even, odd = row_means[0::2].mean(), row_means[1::2].mean()
    assert abs(even - odd) > 0  # two row gains, drawn
    pixel = residual / row_means[:, None]
    assert pixel.std() == pytest.approx(0.03, rel=4 / np.sqrt(2 * a.size))


def test_same_seed_same_burst_and_sources_are_independent():
    a = simulate_burst(shape=(32, 48), n_frames=3, seed=4)
    b = simulate_burst(shape=(32, 48), n_frames=3, seed=4)
    for f in dataclasses.fields(a):
        np.testing.assert_array_equal(np.asarray(getattr(a, f.name)), np.asarray(getattr(b, f.name)))
    c = simulate_burst(shape=(32, 48), n_frames=3, seed=5)
    assert not np.array_equal(a.frames, c.frames)
    noisier = simulate_burst(shape=(32, 48), n_frames=3, seed=4, sensor=with_overrides(PAPER, read_noise_e=80.0))
    np.testing.assert_array_equal(noisier.homographies, a.homographies)
    np.testing.assert_array_equal(noisier.gain, a.gain)
    np.testing.assert_array_equal(noisier.ideal, a.ideal)


def test_rendering_follows_the_homography_convention():
    # H_t_ref maps reference pixel p to p + (3, 2) in frame t, so frame t at
    # (y + 2, x + 3) sees what the reference sees at (y, x)
    scene = procedural_scene((140, 160), np.random.default_rng(0))
    shift = np.array([[1.0, 0, 3], [0, 1.0, 2], [0, 0, 1.0]])
    ref = render(scene, np.eye(3), (50, 60), scale=2, margin=10, supersample=3)
    moved = render(scene, shift, (50, 60), scale=2, margin=10, supersample=3)
    np.testing.assert_allclose(moved[2:, 3:], ref[:-2, :-3], rtol=0, atol=1e-5)


def test_noise_statistics_match_the_sensor_model():
    # still camera, no FPN: two frames differ by temporal noise only;
    # var = 2 * (shot + read) in DN^2 plus 2/12 of rounding
    sensor = with_overrides(PRESETS["raw12"], fpn_pixel=0.0, read_noise_e=20.0, cfa=None)
    burst = simulate_burst(shape=(128, 160), n_frames=2, sensor=sensor, shake=STILL, seed=2)
    np.testing.assert_array_equal(burst.ideal[0], burst.ideal[1])
    diff = burst.frames[1].astype(np.float64) - burst.frames[0]
    g = sensor.dn_per_e
    expected = np.mean(2 * (burst.ideal[0] / g + sensor.read_noise_e**2) * g**2) + 2 / 12
    # a variance from n samples has relative sd sqrt(2/n) = 0.5 % here; allow 4 sd
    assert diff.var() == pytest.approx(expected, rel=4 * np.sqrt(2 / diff.size))


def test_paper_sensor_reproduces_the_published_mse_before():
    # docs/method.md section 4: about 32 DN^2 with 5 % FPN, noise floor about 1 DN^2
    burst = simulate_burst(shape=(120, 160), n_frames=1, seed=2)
    mse = np.mean((burst.frames[0] - burst.ideal[0]) ** 2)
    floor = np.mean((burst.frames[0] / burst.gain - burst.ideal[0]) ** 2)
    assert 20 < mse < 50
    assert 0.8 < floor < 1.6


def test_frame_zero_is_the_reference():
    burst = simulate_burst(shape=(32, 48), n_frames=4, seed=1)
    np.testing.assert_array_equal(burst.homographies[0], np.eye(3))
    assert not np.allclose(burst.homographies[1], np.eye(3))


def test_cfa_mosaic_samples_one_colour_per_site():
    sensor = with_overrides(PRESETS["raw12"], fpn_pixel=0.0)
    burst = simulate_burst(shape=(64, 64), n_frames=1, sensor=sensor, seed=1)
    g = burst.ideal[0]
    # a colour scene: the R and B planes differ from the G planes on average
    assert abs(g[0::2, 0::2].mean() - g[1::2, 1::2].mean()) > 1.0


@pytest.mark.parametrize("fmt", ["exr", "dng"])
def test_saved_burst_reads_back_exactly(tmp_path, fmt):
    burst = simulate_burst(shape=(32, 48), n_frames=3, sensor=PRESETS["raw12"], seed=6)
    paths = save_burst(burst, tmp_path, fmt=fmt, parameters={"seed": 6})
    frames = io.read_stack(paths)
    for frame, counts in zip(frames, burst.frames):
        np.testing.assert_array_equal(frame.data[:, :, 0], counts.astype(np.float32) - 256)
        assert frame.info.cfa == "RGGB" and frame.info.saturation == 4095 - 256
    truth = load_truth(tmp_path)
    np.testing.assert_array_equal(truth.gain, burst.gain)
    np.testing.assert_array_equal(truth.ideal, burst.ideal[0])
    np.testing.assert_array_equal(truth.homographies, burst.homographies)  # JSON keeps float64 exactly
    assert json.loads((tmp_path / "truth" / "simulation.json").read_text())["seed"] == 6


def test_user_scene_is_used(rng):
    scene = np.zeros((50, 50), np.float32)
    scene[:, 25:] = 1.0
    burst = simulate_burst(shape=(32, 32), n_frames=1, scene=scene, shake=STILL,
                           sensor=with_overrides(PAPER, fpn_pixel=0.0), seed=1)
    left, right = burst.ideal[0][:, :8].mean(), burst.ideal[0][:, -8:].mean()
    assert left < 1 and right > 100


def test_lens_blur_band_limits_the_scene_and_is_off_by_default():
    sharp = simulate_burst(shape=(48, 64), n_frames=1, seed=3)
    default = simulate_burst(shape=(48, 64), n_frames=1, seed=3, optics_sigma_px=0.0)
    np.testing.assert_array_equal(sharp.frames, default.frames)
    blurred = simulate_burst(shape=(48, 64), n_frames=1, seed=3, optics_sigma_px=1.0)
    energy = lambda img: np.mean(np.diff(img.astype(np.float64), axis=1) ** 2)  # noqa: E731
    assert energy(blurred.ideal[0]) < 0.7 * energy(sharp.ideal[0])
    assert blurred.ideal[0].mean() == pytest.approx(sharp.ideal[0].mean(), rel=0.02)  # light is kept


def test_dead_leaves_has_natural_image_statistics():
    # natural images (and the ISO 19567-2 chart) have power ~ f**-2 between
    # the smallest and the largest structure; measured slopes -1.6 to -1.8
    img = dead_leaves((512, 512), np.random.default_rng(0), r_min=2.0)
    assert img.dtype == np.float32 and 0.05 <= img.min() and img.max() <= 0.95
    assert np.mean(img == 0.5) < 0.01  # the background is covered
    power = np.abs(np.fft.fft2(img - img.mean())) ** 2
    f = np.hypot(np.fft.fftfreq(512)[:, None], np.fft.fftfreq(512)[None, :])
    band = (f > 4 / 512) & (f < 1 / (2 * np.pi * 2.0))
    slope = np.polyfit(np.log(f[band]), np.log(power[band]), 1)[0]
    assert -2.3 < slope < -1.3
    colour = dead_leaves((64, 64), np.random.default_rng(0), r_min=2.0, colour=True)
    assert colour.shape == (64, 64, 3) and np.ptp(colour[..., 0] - colour[..., 1]) > 0.1


def test_named_scenes():
    smooth = simulate_burst(shape=(40, 48), n_frames=1, seed=2)
    leaves = simulate_burst(shape=(40, 48), n_frames=1, seed=2, scene="dead-leaves")
    energy = lambda img: np.mean(np.diff(img.astype(np.float64), axis=1) ** 2)  # noqa: E731
    assert energy(leaves.ideal[0]) > energy(smooth.ideal[0])  # sharper
    np.testing.assert_array_equal(leaves.gain, smooth.gain)  # only the scene changed
    with pytest.raises(ValueError, match="dead-leaves"):
        simulate_burst(shape=(8, 8), n_frames=1, scene="leaves")
    with pytest.raises(ValueError, match="r_min"):
        dead_leaves((8, 8), np.random.default_rng(0), r_min=0.0)


@pytest.mark.parametrize("shake", [Shake(wobble_px=1.0), Shake(distortion_px=1.0)], ids=["wobble", "distortion"])
def test_wave_truth_positions_match_the_rendered_frames(shake):
    # a rolling-shutter wobble or a 2-D distortion: no single warp explains it, Burst.positions does
    import cv2

    from gainfpn_cli.geometry.warps import positions_from_homography

    shape = (120, 160)
    burst = simulate_burst(shape=shape, n_frames=3, seed=4, shake=shake, scene="procedural")
    assert burst.waves is not None and np.all(burst.waves[0, :, 1] == 0)
    core = np.s_[12:-12, 12:-12]
    for t in (1, 2):
        errors = {}
        for label, pos in (("truth", burst.positions(t)), ("warp", positions_from_homography(burst.homographies[t], shape))):
            for step in ((0, 0), (-0.2, 0), (0.2, 0), (0, -0.2), (0, 0.2)):
                q = (pos + step).astype(np.float32)
                seen = cv2.remap(burst.ideal[t], q[..., 0], q[..., 1], cv2.INTER_CUBIC)
                errors[label, step] = np.sqrt(np.mean((seen - burst.ideal[0])[core] ** 2))
        off = [errors[key] for key in errors if key[0] == "truth" and key[1] != (0, 0)]
        assert errors["truth", (0, 0)] < min(off)  # exact to < 0.2 px along both axes
        assert errors["truth", (0, 0)] < 0.5 * errors["warp", (0, 0)]
    plain = simulate_burst(shape=shape, n_frames=3, seed=4, scene="procedural")
    assert plain.waves is None
    np.testing.assert_array_equal(plain.positions(1), positions_from_homography(plain.homographies[1], shape))


def test_defects_are_drawn_by_kind_and_change_no_healthy_photosite():
    from gainfpn_cli.sim.simulate import DEFECT_SHARES, HOT_OFFSET_NOISE
    from gainfpn_cli.solve.defects import DEAD, HOT, KINDS, STUCK

    sensor = PRESETS["raw12"]
    clean = simulate_burst(shape=(120, 160), n_frames=4, sensor=sensor, seed=3)
    burst = simulate_burst(shape=(120, 160), n_frames=4, sensor=sensor, seed=3, defects=0.01)
    assert clean.defects is None
    counts = {kind: int((burst.defects == code).sum()) for kind, code in KINDS.items()}
    assert counts == {"hot": 134, "dead": 29, "stuck": 29}  # 192 = 1 % in DEFECT_SHARES
    assert counts["hot"] == round(DEFECT_SHARES["hot"] * 192)
    healthy = burst.defects == 0
    np.testing.assert_array_equal(burst.frames[:, healthy], clean.frames[:, healthy])
    np.testing.assert_array_equal(burst.gain, clean.gain)
    stuck = burst.frames[:, burst.defects == STUCK].astype(int)
    assert np.all(stuck == stuck[0])  # one reading in every frame
    dead = burst.frames[:, burst.defects == DEAD].astype(float) - sensor.black_level
    assert np.abs(dead).max() <= 5 * sensor.read_noise_e * sensor.dn_per_e + 1  # no light: read noise only
    # hot: an offset of 5-50x the reference frame's noise, on top of the clean reading
    hot = burst.defects == HOT
    excess = (burst.frames[0, hot].astype(float) - clean.frames[0, hot]) / sensor.dn_per_e
    noise = np.sqrt(clean.gain[hot] * clean.ideal[0, hot] / sensor.dn_per_e + sensor.read_noise_e**2)
    ratio = excess / noise
    low, high = HOT_OFFSET_NOISE
    assert np.median(ratio) == pytest.approx(np.sqrt(low * high), rel=0.3)  # log-uniform: median at the geometric mean
    assert np.quantile(ratio, 0.05) > 0.8 * low


def test_simulate_writes_the_defects_beside_the_truth(tmp_path):
    from click.testing import CliRunner

    from gainfpn_cli.cli import main

    result = CliRunner().invoke(main, ["simulate", str(tmp_path / "d"), "--size", "64x48", "--frames", "3",
                                       "--defects", "0.01", "-q"])
    assert result.exit_code == 0, result.output
    truth = load_truth(tmp_path / "d")
    burst = simulate_burst(shape=(48, 64), n_frames=3, seed=0, defects=0.01)
    np.testing.assert_array_equal(truth.defects, burst.defects)
    assert json.loads((tmp_path / "d" / "truth" / "simulation.json").read_text())["defects"] == 0.01
    CliRunner().invoke(main, ["simulate", str(tmp_path / "c"), "--size", "64x48", "--frames", "3", "-q"])
    assert load_truth(tmp_path / "c").defects is None
