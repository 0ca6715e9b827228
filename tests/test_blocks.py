import numpy as np
import pytest

from gainfpn_cli import metrics
from gainfpn_cli.errors import EstimationError
from gainfpn_cli.geometry.warps import positions_from_homography
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.blocks import solve_paper
from gainfpn_cli.solve.kkt import SolveOptions

NOISELESS = with_overrides(PRESETS["paper"], read_noise_e=0.0, shot_noise=False, adc_bits=16)


def _positions(burst, shape=None):
    shape = shape or burst.frames.shape[1:]
    return np.stack([positions_from_homography(H, shape) for H in burst.homographies[1:]])


def _flat_burst(shape=(30, 40), shake=Shake(translation_px=1.0, rotation_deg=0.1), n_frames=6, seed=1):
    """A flat, noise-free scene: every frame is ``s * a`` whatever the motion."""
    burst = simulate_burst(shape=shape, n_frames=n_frames, seed=seed, sensor=NOISELESS,
                           scene=np.full((8, 8), 0.5, np.float32), shake=shake)
    return burst, burst.ideal * burst.gain  # unquantised


def _check_sane(result, options=SolveOptions()):
    assert np.all(np.isfinite(result.k)) and np.all(np.isfinite(result.confidence))
    est = result.confidence > 0
    low, high = options.k_range
    assert np.all((result.k[est] >= low * 0.9) & (result.k[est] <= high * 1.1))
    assert np.all(result.k[~est] == 1.0)
    if est.any():
        assert result.k[est].mean() == pytest.approx(1.0, abs=1e-5)  # the gauge


def test_flat_noise_free_scene_recovers_the_gain():
    burst, frames = _flat_burst()
    result = solve_paper(frames, _positions(burst), workers=1)
    _check_sane(result)
    est = result.confidence > 0
    assert est.mean() > 0.95
    # The paper interpolates k and i separately, (T k)(T i) instead of T(k i):
    # on a flat scene that leaves a bias of order var(a) within a stencil
    # (~0.15 % for 5 % FPN), which the weakly observed low spatial frequencies
    # (docs/method.md section 5.3) amplify; measured 0.74 %. A wrong trajectory convention
    # leaves more than the input 5 %, so 1 % separates right from wrong.
    assert metrics.residual_fpn_percent(result.k, burst.gain, est) < 1.0


def test_constant_gain_gives_constant_k():
    sensor = with_overrides(NOISELESS, fpn_pixel=0.0)
    burst = simulate_burst(shape=(30, 40), n_frames=5, seed=2, sensor=sensor, scene=np.full((4, 4), 0.4, np.float32))
    result = solve_paper(burst.ideal, _positions(burst), workers=1)
    np.testing.assert_allclose(result.k[result.confidence > 0], 1.0, atol=1e-6)


def test_inputs_are_not_modified():
    burst, frames = _flat_burst()
    pos = _positions(burst)
    frames_copy, pos_copy = frames.copy(), pos.copy()
    solve_paper(frames, pos, workers=1)
    np.testing.assert_array_equal(frames, frames_copy)
    np.testing.assert_array_equal(pos, pos_copy)


def test_zero_motion_is_reported_not_guessed():
    burst, frames = _flat_burst(shake=Shake(translation_px=0.0, rotation_deg=0.0))
    with pytest.raises(EstimationError, match="no motion"):
        solve_paper(frames, _positions(burst), workers=1)


def test_static_frames_are_left_out_and_counted():
    burst, frames = _flat_burst()
    pos = _positions(burst)
    ys, xs = np.mgrid[0:30, 0:40]
    pos[1] = np.stack([xs, ys], axis=-1)  # frame 2 did not move
    result = solve_paper(frames, pos, workers=1)
    assert result.stats.static_frames == 1
    _check_sane(result)


def test_worker_count_does_not_change_a_bit():
    burst = simulate_burst(shape=(48, 64), n_frames=5, seed=4)
    frames = burst.frames.astype(np.float32)
    one = solve_paper(frames, _positions(burst), workers=1, saturation=burst.saturation)
    two = solve_paper(frames, _positions(burst), workers=2, saturation=burst.saturation)
    np.testing.assert_array_equal(one.k, two.k)
    np.testing.assert_array_equal(one.confidence, two.confidence)
    assert one.stats == two.stats


@pytest.mark.parametrize("block_size", [1, 2, 7])
def test_any_block_size_is_safe(block_size):
    burst = simulate_burst(shape=(24, 30), n_frames=4, seed=5)
    result = solve_paper(burst.frames.astype(np.float32), _positions(burst), block_size=block_size, workers=1,
                         saturation=burst.saturation)
    _check_sane(result)


def test_block_as_large_as_the_frame():
    burst, frames = _flat_burst(shape=(24, 28))
    result = solve_paper(frames, _positions(burst), block_size=64, workers=1)
    assert result.stats.blocks == 1
    _check_sane(result)
    est = result.confidence > 0
    # one block, one gauge: the same product-of-averages bound as above
    assert metrics.residual_fpn_percent(result.k, burst.gain, est) < 1.0


def test_sparse_path_gives_the_dense_answer(monkeypatch):
    # the same whole-frame block solved by the dense null-space Cholesky and
    # by the sparse KKT LU; a loose safety limit so neither path regularises
    burst, frames = _flat_burst(shape=(24, 28))
    options = SolveOptions(max_condition=1e12)
    dense = solve_paper(frames, _positions(burst), block_size=64, options=options, workers=1)
    monkeypatch.setattr("gainfpn_cli.solve.blocks.DENSE_MAX", 100)
    sparse = solve_paper(frames, _positions(burst), block_size=64, options=options, workers=1)
    assert dense.stats.regularised == sparse.stats.regularised == 0
    np.testing.assert_allclose(sparse.k, dense.k, rtol=1e-7)


@pytest.mark.parametrize("lam", [0.0, 1e-12, 1e6])
def test_lambda_extremes_are_safe(lam):
    burst = simulate_burst(shape=(24, 30), n_frames=4, seed=6)
    options = SolveOptions(lam=lam)
    result = solve_paper(burst.frames.astype(np.float32), _positions(burst), options=options, workers=1,
                         saturation=burst.saturation)
    _check_sane(result, options)


def test_trajectories_leaving_the_frame():
    # every frame shifted 10 px right: reference pixels in the last 10 columns
    # land outside every frame, have no equation, and are reported, not invented
    burst, frames = _flat_burst(shape=(20, 30))
    ys, xs = np.mgrid[0:20, 0:30].astype(float)
    pos = np.stack([np.stack([xs + 10 + 0.3 * t, ys + 0.2 * t], axis=-1) for t in range(1, len(frames))])
    result = solve_paper(frames, pos, workers=1)
    _check_sane(result)
    assert np.all(result.confidence[:, 20:] == 0) and np.all(result.k[:, 20:] == 1.0)
    assert np.all(result.confidence[:15, :15] > 0)
    assert result.stats.unestimated_pixels >= 20 * 10


def test_saturated_and_zero_pixels_are_excluded():
    burst = simulate_burst(shape=(30, 40), n_frames=5, seed=7)
    frames = burst.frames.astype(np.float32)
    frames[:, :10, :] = burst.saturation  # a blown-out band
    frames[:, -5:, :] = 0.0  # and a dead one
    result = solve_paper(frames, _positions(burst), workers=1, saturation=burst.saturation)
    _check_sane(result)
    assert np.all(result.confidence[:8] == 0) and np.all(result.k[:8] == 1.0)
    clean = solve_paper(burst.frames.astype(np.float32), _positions(burst), workers=1, saturation=burst.saturation)
    assert result.stats.rows < clean.stats.rows


def test_nothing_usable_leaves_everything_unestimated():
    burst, frames = _flat_burst()
    result = solve_paper(np.zeros_like(frames), _positions(burst), workers=1)
    assert result.stats.unestimated_pixels == frames[0].size
    np.testing.assert_array_equal(result.k, 1.0)


def test_validates_shapes():
    with pytest.raises(ValueError, match="frames must have shape"):
        solve_paper(np.zeros((1, 4, 4)), np.zeros((0, 4, 4, 2)))
    with pytest.raises(ValueError, match="positions must have shape"):
        solve_paper(np.zeros((2, 4, 4)), np.zeros((1, 4, 5, 2)))


def test_paper_mode_beats_no_correction_on_a_noisy_textured_burst():
    # the paper's sensor and true motion: the published form gave 2.8x
    # (docs/method.md section 4). With per-block conditioning it must at least
    # halve the MSE on any seed; measured 5-12x on 120x160 bursts.
    burst = simulate_burst(shape=(64, 80), n_frames=8, seed=3, shake=Shake(translation_px=0.7, rotation_deg=0.1))
    frames = burst.frames.astype(np.float32)
    result = solve_paper(frames, _positions(burst), workers=1, saturation=burst.saturation)
    mask = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], 6)
    before = metrics.mse(frames[0], burst.ideal[0], mask)
    after = metrics.mse(result.k * frames[0], burst.ideal[0], mask)
    assert before / after > 2.0


def test_paper_mode_reproduces_the_published_ratio():
    # docs/method.md section 4: the published form gave 2.8x on the paper's sensor.
    # On the photograph-like dead-leaves scene, true motion, the per-burst
    # ratio spreads 1.3-3.4x with the scene and shake (30 bursts of 96x128:
    # median 2.0; 15 of 120x160: median 2.2; 6 of 240x320: median 2.6), so
    # the median of five bursts is checked against the published regime
    # (measured 2.3 here); the accurate mode gets 12-17x on the same bursts.
    ratios = []
    for seed in range(5):
        burst = simulate_burst(shape=(120, 160), n_frames=8, seed=seed, scene="dead-leaves")
        frames = burst.frames.astype(np.float32)
        result = solve_paper(frames, _positions(burst), workers=1, saturation=burst.saturation)
        mask = (result.confidence > 0) & metrics.interior_mask(frames.shape[1:], 6)
        ratios.append(metrics.mse(frames[0], burst.ideal[0], mask) / metrics.mse(result.k * frames[0], burst.ideal[0], mask))
    assert 1.6 <= np.median(ratios) <= 3.6, ratios


@pytest.mark.parametrize("shape", [(2, 2), (3, 3), (8, 8), (1, 20), (20, 1)])
def test_tiny_frames(shape):
    a = 1 + 0.05 * np.random.default_rng(0).standard_normal(shape)
    frames = np.stack([100.0 * a] * 4).astype(np.float32)
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    step = (0.3 if w > 1 else 0.0, 0.2 if h > 1 else 0.0)
    pos = np.stack([np.stack([xs + step[0] * t, ys + step[1] * t], axis=-1) for t in range(1, 4)])
    result = solve_paper(frames, pos, workers=1)
    _check_sane(result)
