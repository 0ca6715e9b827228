"""How aliased a burst is (solve/aliasing.py) and the solver ``solver.method: auto`` picks from it."""

import json

import numpy as np
import pytest
from helpers import run_cli
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.aliasing import aliasing, cubic_weights, noise_gain
from gainfpn_cli.solving import ALIASED


@settings(max_examples=30, deadline=None)
@given(step=st.integers(0, 31))
def test_cubic_weights_are_opencvs_kernel(step):
    # OpenCV's INTER_CUBIC sampling an impulse at each of the 4 taps (it rounds positions to 1/32 px)
    import cv2

    phase = step / 32
    impulse = np.zeros((1, 16), np.float32)
    impulse[0, 8] = 1
    x = np.array([[8 - offset + phase for offset in (-1, 0, 1, 2)]], np.float32)
    sampled = cv2.remap(impulse, x, np.zeros_like(x), cv2.INTER_CUBIC)[0]
    np.testing.assert_allclose(sampled, [float(w) for w in cubic_weights(np.array(phase))], atol=1e-6)


def test_noise_gain_known_answers():
    # Keys' kernel, a = -0.75: weights (-3/32, 19/32, 19/32, -3/32) at half a pixel
    half = 2 * ((3 / 32) ** 2 + (19 / 32) ** 2)
    np.testing.assert_allclose(noise_gain(np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.5]])), [1.0, half, half**2])


def test_white_noise_alone_is_not_aliasing():
    # a flat scene seen through noise only: the excess is 0 to its sampling error
    rng = np.random.default_rng(5)
    frames = 100 + rng.normal(0, 2, (8, 128, 128)).astype(np.float32)
    shifts = rng.uniform(-3, 3, (8, 2))
    shifts[0] = 0
    H = np.array([[[1, 0, x], [0, 1, y], [0, 0, 1.0]] for x, y in shifts])
    measured = aliasing(frames, GlobalWarp(H)).excess
    assert abs(measured) < 0.03


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sharp_scene_is_aliased_and_a_blurred_one_is_not(seed):
    # measured (seeds 1-3): sharp dead leaves 0.51 / 0.36 / 0.44, through a 1 px lens blur 0.03 / 0.02 / -0.07
    def excess(blur):
        burst = simulate_burst(shape=(96, 128), n_frames=8, scene="dead-leaves", seed=seed, optics_sigma_px=blur)
        frames = burst.frames.astype(np.float32) - PRESETS["paper"].black_level
        good = (frames > 0) & (frames < 255 - PRESETS["paper"].black_level)
        return aliasing(frames, GlobalWarp(np.asarray(burst.homographies)), good=good).excess

    assert excess(0.0) > 2 * ALIASED
    assert excess(1.0) < ALIASED / 2


@pytest.mark.parametrize("blur, method", [(0.0, "scene"), (1.5, "accurate")])
def test_auto_reports_its_choice_and_why(tmp_path, blur, method):
    sim, out = tmp_path / "sim", tmp_path / "out"
    run_cli("simulate", str(sim), "--size", "128x96", "--scene", "dead-leaves", "--seed", "3", "--blur", str(blur),
            "-q")
    run_cli("estimate", str(sim), "-o", str(out), "-q")
    report = json.loads((out / "report.json").read_text())
    assert report["solver"]["method"] == method
    assert report["planes"]["Y"]["method"] == method
    assert ("not aliased" in report["solver"]["reason"]) == (method == "accurate")
    assert (report["solver"]["aliasing"] >= ALIASED) == (method == "scene")
