"""The two predictions of the scene a photosite sees (solve.predict): exact where the motion is
whole photosites, never the photosite itself, and the sharper one sharper on an aliased plane."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gainfpn_cli.geometry.planes import plane_views
from gainfpn_cli.geometry.resample import positions
from gainfpn_cli.geometry.warps import GlobalWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve import predict, stacks


def _everywhere(t, frame):
    return np.ones(frame.shape, bool)


def _shifted_burst(shifts, shape=(40, 48), seed=0):
    """A static random scene seen through whole-photosite shifts ``(dx, dy)`` per frame, and its warp
    (``H_t_ref``: the reference pixel ``q`` is at ``q + shift`` in frame t)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    scene = rng.uniform(10, 100, (h + 20, w + 20)).astype(np.float32)
    frames = np.stack([scene[10 + dy:10 + dy + h, 10 + dx:10 + dx + w] for dx, dy in shifts])
    homographies = np.array([[[1, 0, -dx], [0, 1, -dy], [0, 0, 1]] for dx, dy in shifts], np.float64)
    return frames, GlobalWarp(homographies)


def test_whole_photosite_shifts_are_predicted_exactly():
    # every other frame lands on photosites: the two nearest readings are the scene itself
    frames, warp = _shifted_burst([(0, 0), (1, 0), (0, 2), (-1, 1), (2, -1)])
    x, valid = predict.nearest_along(frames, _everywhere, warp)
    assert valid[:, 6:-6, 6:-6].all()
    np.testing.assert_array_equal(x[valid], frames[valid])


def test_a_photosite_never_predicts_itself():
    # without motion every other frame's nearest photosite to the point is the photosite itself
    frames, warp = _shifted_burst([(0, 0)] * 5)
    frames[:, 20, 20] = 4000.0  # a defect reading far off in every frame
    x, valid = predict.nearest_along(frames, _everywhere, warp)
    assert not valid.any()
    # with motion in some frames: a point is predicted only by the frames that moved
    frames, warp = _shifted_burst([(0, 0), (0, 0), (1, 0), (0, 1)])
    frames[:2, 20, 20] = 4000.0
    x, valid = predict.nearest_along(frames, _everywhere, warp)
    assert valid[0, 20, 20] and x[0, 20, 20] < 200  # from frames 2 and 3, not from frame 1


@pytest.mark.parametrize("threads", [2, 3, 200])
def test_strips_of_rows_on_threads_find_the_same_readings(threads, monkeypatch):
    # each frame's rows are searched a strip at a time on threads (7 rows a strip on one thread; more
    # threads than rows: one row each)
    monkeypatch.setattr(stacks, "STRIP_READINGS", 6 * 80 * 7)
    burst = simulate_burst(shape=(60, 80), n_frames=6, sensor=PRESETS["paper"], seed=3)
    frames, warp = burst.frames.astype(np.float32), GlobalWarp(burst.homographies)
    x, valid = predict.nearest_along(frames, _everywhere, warp)
    x_threads, valid_threads = predict.nearest_along(frames, _everywhere, warp, threads=threads)
    assert valid.mean() > 0.8
    np.testing.assert_array_equal(valid_threads, valid)
    np.testing.assert_array_equal(x_threads, x)


class _AsMaps:
    """A warp whose pairs are position maps ``(h, w, 2)`` (as a field or layered warp's), here those
    of ``warp``'s homographies."""

    def __init__(self, warp):
        self.warp = warp

    def pair(self, s, t, region):
        return positions(self.warp.pair(s, t, region), region[2:]).astype(np.float32)


def test_position_maps_predict_as_their_homographies():
    sensor = PRESETS["raw12"]
    burst = simulate_burst(shape=(60, 80), n_frames=6, sensor=dataclasses.replace(sensor, cfa=None), seed=3)
    frames, warp = burst.frames.astype(np.float32), GlobalWarp(burst.homographies)
    x, valid = predict.nearest_along(frames, _everywhere, warp)
    x_map, valid_map = predict.nearest_along(frames, _everywhere, _AsMaps(warp))
    assert valid.mean() > 0.8
    # float32 positions: a tie between two frames' distances may fall the other way, nothing else
    assert (valid_map == valid).all() and np.mean(x_map[valid] == x[valid]) > 0.999


@pytest.mark.parametrize("preset", ["raw12", "paper"])
def test_the_sharper_prediction_errs_less_on_an_aliased_burst(preset):
    # noise-free dead leaves: every colour plane of the mosaic, and the 8-bit sensor's one plane,
    # sampled coarser than their edges. Median relative error (docs/bench/defects.py predict):
    # raw12 1.9-2.4 % -> 0.8-1.0 %, 8-bit 0.30 % -> 0.08 %
    sensor = dataclasses.replace(PRESETS[preset], shot_noise=False, read_noise_e=0.0, fpn_pixel=0.0)
    burst = simulate_burst(shape=(120, 160), n_frames=8, sensor=sensor, scene="dead-leaves", seed=0)
    warp = GlobalWarp(burst.homographies)
    for _, pick, S in plane_views(sensor.cfa, ("Y",)):
        ideal = np.ascontiguousarray(pick(burst.ideal[..., None]), np.float32)
        median, valid, from_frames = predict.scene_along(ideal, _everywhere, warp.conjugate(S))
        sharp, known = predict.nearest_along(ideal, _everywhere, warp.conjugate(S))
        both = valid & from_frames & known & (ideal > 0.05 * ideal.max())
        assert both.mean() > 0.5
        errors = [np.median(np.abs(x[both] / ideal[both] - 1)) for x in (median, sharp)]
        assert errors[1] < 0.6 * errors[0]
