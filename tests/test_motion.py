from pathlib import Path

import numpy as np
import pytest

from gainfpn_cli.burst import LoadedBurst
from gainfpn_cli.config import load_config
from gainfpn_cli.errors import EstimationError
from gainfpn_cli.geometry.warps import positions_from_flow, positions_from_homography, trajectory_rms
from gainfpn_cli.motion.estimate import estimate_motion
from gainfpn_cli.motion.masks import moving_masks
from gainfpn_cli.pipeline import estimate
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.simulate import simulate_burst

SHAPE = (200, 260)


def _worst(burst, result):
    return max(trajectory_rms(result.homographies[t], burst.homographies[t], SHAPE) for t in range(1, len(burst.frames)))


def test_positions_follow_the_conventions():
    H = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]])
    pos = positions_from_homography(H, (4, 5))
    assert pos.shape == (4, 5, 2)
    np.testing.assert_array_equal(pos[1, 2], [2 + 3, 1 - 2])  # pixel (x=2, y=1) -> (5, -1)
    flow = np.zeros((4, 5, 2))
    flow[..., 0], flow[..., 1] = 3.0, -2.0
    np.testing.assert_array_equal(positions_from_flow(flow), pos)
    with pytest.raises(ValueError, match=r"flow_xy must have shape \(H, W, 2\)"):
        positions_from_flow(np.zeros((4, 5)))


SHAKE4 = Shake(translation_px=2.5, rotation_deg=0.5)
DRIFT = Shake(translation_px=1.0, rotation_deg=0.2, drift_px=25)


def _reported_worst(burst, report):
    """Worst frame's trajectory error of the homographies report.json gives (frame pixels)."""
    Hs = [np.array(f.homography) for f in report.motion.frames]
    return max(trajectory_rms(H, burst.homographies[t], SHAPE) for t, H in enumerate(Hs, start=1))


# Seeds 5 and 6 were not used to choose TRACK_SIGMA, TRACK_QUALITY or INLIER_PX.
# The unit suite keeps the two bursts where the first estimate misses and the round meets it.
@pytest.mark.parametrize("seed, shake", [pytest.param(5, Shake(), marks=pytest.mark.slow),
                                         pytest.param(6, Shake(), marks=pytest.mark.slow), (5, SHAKE4),
                                         pytest.param(6, SHAKE4, marks=pytest.mark.slow),
                                         pytest.param(5, DRIFT, marks=pytest.mark.slow), (6, DRIFT)],
                         ids=["shake-5", "shake-6", "shake4px-5", "shake4px-6", "drift25px-5", "drift25px-6"])
def test_global_warp_is_sub_pixel_accurate_despite_fpn(seed, shake):
    # issue 4: RMS trajectory error <= 0.05 px with 5 % gain FPN, asserted on
    # the worst frame of the burst. On this smooth scene the gain pattern
    # pulls the first estimate toward zero motion (shake4px-5: 0.083 px,
    # drift25px-6: 0.061 px); a refinement round tracks again on the frames
    # corrected by k. Measured over seeds 3-10 x these shakes (24 bursts):
    # first estimate worst 0.083 px (6 over 0.05), refined 0.048 px (none).
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=seed, shake=shake)
    frames = burst.frames.astype(np.float32) - burst.sensor.black_level
    loaded = LoadedBurst([Path(f"f{i}.exr") for i in range(len(frames))], frames[..., None].copy(), None, ("Y",),
                         None, 0)
    result = estimate(loaded, load_config(overrides={"solver.workers": 1, "motion.refine_rounds": 1}))
    refined = _reported_worst(burst, result.report)
    assert refined <= 0.05
    assert "refined on frames corrected by k (round 1)" in result.report.motion.reason
    if (seed, shake) in ((5, SHAKE4), (6, DRIFT)):  # where the first estimate misses, the round is what meets it
        assert _worst(burst, estimate_motion(frames)) > 0.05 > refined


@pytest.mark.parametrize("shake", [Shake(), SHAKE4, DRIFT], ids=["shake", "shake4px", "drift25px"])
def test_global_warp_on_dead_leaves_is_sub_pixel_accurate(shake):
    # issue 4's 0.05 px on the scene with sharp edges at every scale; seeds 3-10
    # measured worst frame 0.033 px over 24 bursts, held-out seed 11 0.014-0.019 px
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=11, shake=shake, scene="dead-leaves")
    assert _worst(burst, estimate_motion(burst.frames.astype(np.float32))) <= 0.05


@pytest.mark.parametrize("seed, shake, limit", [(5, Shake(), 0.05), (6, Shake(), 0.05), (7, DRIFT, 0.1)],
                         ids=["shake-5", "shake-6", "drift25px-7"])
def test_a_moving_object_does_not_move_the_global_warp(seed, shake, limit):
    # issue 4: an object covering 10 % of the frame moves on its own. Worst
    # frame measured without / with it: 0.028 / 0.035, 0.047 / 0.049 and, for
    # the drift (where MAGSAC once preferred the object's 48 crisp corners to
    # 96 background ones and missed by 29 px), 0.032 / 0.063 px.
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=seed, shake=shake, moving_object=0.1)
    assert burst.moving.mean() == pytest.approx(0.1, abs=0.02)
    result = estimate_motion(burst.frames.astype(np.float32))
    assert _worst(burst, result) <= limit


def test_the_dominant_motion_is_the_one_that_spans_the_frame():
    from gainfpn_cli.motion.fit import coverage, fit_models

    rng = np.random.default_rng(0)
    spread = rng.uniform([0, 0], [320, 240], (150, 2))  # a soft background: fewer corners, tracked less well
    crisp = rng.uniform([200, 150], [260, 200], (200, 2))  # a crisp object in one corner: more corners
    src = np.vstack([spread, crisp])
    dst = np.vstack([spread + [1.0, 0.5] + rng.normal(0, 0.08, spread.shape),
                     crisp + [4.0, -3.0] + rng.normal(0, 0.02, crisp.shape)])
    assert coverage(spread, (240, 320)) > coverage(crisp, (240, 320))
    by_count, inliers = fit_models(src, dst)  # without the frame's shape: the group with most points
    assert inliers[150:].mean() > 0.9 and not inliers[:150].any()
    assert np.allclose(by_count["translation"][:2, 2], [4.0, -3.0], atol=0.01)
    fits, inliers = fit_models(src, dst, shape=(240, 320))
    assert inliers[:150].mean() > 0.8 and not inliers[150:].any()
    np.testing.assert_allclose(fits["translation"][:2, 2], [1.0, 0.5], atol=0.02)


@pytest.mark.parametrize("seed, shake", [(7, Shake()), (14, SHAKE4)], ids=["shake-7", "shake4px-14"])
def test_an_object_does_not_take_or_pull_the_warp_on_large_frames(seed, shake):
    # 480x640 procedural with a 10 % object, homography forced (so that no
    # layer hides the base warp). Seed 7: the soft background gives fewer good
    # corners than the crisp object, and by inlier count the warp followed the
    # object in frame 2 (4.8 px off); chosen by the frame area it spans, worst
    # frame 0.041 px. Seed 14: the object moves 0.5 px in frame 1, within the
    # inlier threshold, and pulled that frame's warp 0.36 px off; fitted
    # without the points of the layer it forms over the burst, 0.024 px.
    shape = (480, 640)
    burst = simulate_burst(shape=shape, n_frames=6, seed=seed, shake=shake, moving_object=0.1)
    result = estimate_motion(burst.frames.astype(np.float32), model="homography")
    assert max(trajectory_rms(result.homographies[t], burst.homographies[t], shape) for t in range(1, 6)) < 0.05


def test_no_corner_is_taken_where_told_to_ignore():
    from gainfpn_cli.motion.track import find_corners, tracking_image

    burst = simulate_burst(shape=SHAPE, n_frames=1, seed=3, scene="dead-leaves")
    frame = burst.frames[0].astype(np.float32)
    ref8 = tracking_image(frame, *np.percentile(frame, [0.5, 99.5]))
    ignore = np.zeros(SHAPE, bool)
    ignore[40:140, 60:200] = True
    everywhere = find_corners(ref8).reshape(-1, 2)
    kept = find_corners(ref8, ignore=ignore).reshape(-1, 2)
    inside = lambda p: ignore[np.round(p[:, 1]).astype(int), np.round(p[:, 0]).astype(int)]  # noqa: E731
    assert inside(everywhere).sum() > 50 and not inside(kept).any()
    assert len(kept) > 0.5 * (~inside(everywhere)).sum()  # the rest of the frame still gets its corners


@pytest.mark.parametrize("seed, shake", [
    pytest.param(6, DRIFT, marks=pytest.mark.slow), (10, DRIFT),
    pytest.param(7, DRIFT, marks=[pytest.mark.slow, pytest.mark.xfail(
        strict=True, reason="a small-frame limit (docs/limits.md): refined worst frame 0.054 px")]),
], ids=["drift25px-6", "drift25px-10", "drift25px-7"])
def test_a_refinement_round_keeps_the_background_warp_despite_an_object(seed, shake):
    # issue 4: the object's pixels are excluded and the rest keeps <= 0.05 px.
    # The first estimate misses here (0.104 and 0.065 px: the gain pattern's
    # pull); a refinement round chooses the model again on the frames
    # corrected by k and tracks no corner the first round masked as moving.
    # Seeds 3-10 x shake / 4 px shake / 25 px drift (24 bursts): first
    # estimate worst 0.104 px (8 over 0.05), refined 0.055 px (2 over: this
    # drift-7 and 4 px shake seed 5, 0.051 px).
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=seed, shake=shake, moving_object=0.1)
    frames = burst.frames.astype(np.float32) - burst.sensor.black_level
    loaded = LoadedBurst([Path(f"f{i}.exr") for i in range(len(frames))], frames[..., None].copy(), None, ("Y",),
                         None, 0)
    result = estimate(loaded, load_config(overrides={"solver.workers": 1, "motion.refine_rounds": 1}))
    assert _reported_worst(burst, result.report) <= 0.05


@pytest.mark.parametrize(
    "shake, expected",
    [
        (Shake(translation_px=2.0, rotation_deg=0.0), "translation"),
        (Shake(translation_px=2.0, rotation_deg=0.5), "affine"),
        (Shake(translation_px=2.0, rotation_deg=0.2, perspective=3e-5), "homography"),
    ],
)
def test_the_simplest_model_the_motion_needs_is_chosen(shake, expected):
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=7, shake=shake)
    result = estimate_motion(burst.frames.astype(np.float32))
    assert result.model == expected, result.reason
    assert "GRIC" in result.reason


def test_a_forced_model_is_used():
    burst = simulate_burst(shape=SHAPE, n_frames=4, seed=7, shake=Shake(rotation_deg=0.0))
    result = estimate_motion(burst.frames.astype(np.float32), model="homography")
    assert result.model == "homography" and result.reason == "forced by configuration"
    with pytest.raises(ValueError, match="model must be auto or one of"):
        estimate_motion(burst.frames.astype(np.float32), model="flow-ish")


def test_textureless_reference_is_an_error():
    frames = np.full((3, 60, 80), 100.0, np.float32)
    with pytest.raises(EstimationError, match="no texture to track"):
        estimate_motion(frames)


def test_frames_of_unrelated_scenes_are_an_error():
    a = simulate_burst(shape=SHAPE, n_frames=1, seed=1).frames[0]
    b = simulate_burst(shape=SHAPE, n_frames=1, seed=2).frames[0]
    with pytest.raises(EstimationError, match=r"frame 1: .*(points|inliers)"):
        estimate_motion(np.stack([a, b]).astype(np.float32))


def test_a_still_burst_is_reported():
    burst = simulate_burst(shape=SHAPE, n_frames=4, seed=9, shake=Shake(translation_px=0.0, rotation_deg=0.0))
    with pytest.raises(EstimationError, match="no motion"):
        estimate_motion(burst.frames.astype(np.float32))


def _assert_masks_find_the_object(masks, burst, *, textured_found):
    """Per frame: the object's textured pixels found, 85 % of the object, at most 10 % of the rest flagged."""
    import cv2

    for mask, truth, ideal in zip(masks, burst.moving, burst.ideal):
        gradient = np.hypot(cv2.Sobel(ideal, cv2.CV_32F, 1, 0), cv2.Sobel(ideal, cv2.CV_32F, 0, 1))
        textured = truth & (gradient > np.median(gradient))
        assert (mask & textured).sum() >= textured_found * textured.sum()
        assert (mask & truth).sum() >= 0.85 * truth.sum()
        assert (mask & ~truth).sum() <= 0.1 * (~truth).sum()


def test_moving_masks_find_the_object_and_little_else():
    # what matters is the object's textured pixels, where a comparison across
    # the wrong motion errs; flat parts compare equal anyway and may be missed.
    # Measured on 160x200 bursts (seeds 3-5, worst frame): textured part
    # 97.3-99.1 % found, whole object 85-98 %, 5.4-6.5 % of the rest flagged
    # (mostly background the object uncovers); on 240x320, 0.3-1.8 % flagged
    # without an object. (Before the relative criterion: 99.4-99.6 %,
    # 88-99 %, 5.5-8.4 %; 0.5-2.6 %.)
    shape = (160, 200)
    burst = simulate_burst(shape=shape, n_frames=5, seed=3, moving_object=0.1)
    frames = burst.frames.astype(np.float32)
    masks = moving_masks(frames, burst.homographies)
    assert masks.shape == frames.shape and masks.dtype == bool
    _assert_masks_find_the_object(masks, burst, textured_found=0.98)
    still = simulate_burst(shape=shape, n_frames=5, seed=3)
    assert moving_masks(still.frames.astype(np.float32), still.homographies).mean() <= 0.08


@pytest.mark.parametrize("scene", ["procedural", "dead-leaves"])
def test_a_drift_flags_nothing_the_other_frame_does_not_see(scene):
    # no object: a 25 px drift leaves a strip of the reference outside the
    # last frames. It is compared with nothing, so it must not be flagged (it
    # was, and the reference's union over frames lost it for every frame).
    # Held-out seeds 9-11, reference / burst flagged: 9-15 % / 6-8 % before,
    # 1.4-4.3 % / 0.5-1.7 % since
    still = simulate_burst(shape=SHAPE, n_frames=6, seed=11, shake=DRIFT, scene=scene)
    masks = moving_masks(still.frames.astype(np.float32), still.homographies)
    assert masks[0].mean() <= 0.05 and masks.mean() <= 0.02


def test_moving_masks_at_reduced_resolution():
    # large frames are compared area-reduced (mask_factor); measured here with
    # factor 2 on 240x320 (seed 4, worst frame): textured object 99.4 %,
    # object 95 %, rest flagged 4.1 %, 0.05 % of a burst without object (full
    # size: 99.4 %, 95 %, 4.0 %, 0.6 %)
    from gainfpn_cli.motion.masks import MASK_PIXELS, mask_factor

    assert mask_factor((240, 320)) == 1 and mask_factor((3000, 4000)) == 3
    assert mask_factor((1, MASK_PIXELS)) == 1 and mask_factor((1, MASK_PIXELS + 1)) == 2
    shape = (240, 320)
    burst = simulate_burst(shape=shape, n_frames=5, seed=4, moving_object=0.1)
    masks = moving_masks(burst.frames.astype(np.float32), burst.homographies, factor=2)
    assert masks.shape == burst.frames.shape
    _assert_masks_find_the_object(masks, burst, textured_found=0.95)
    still = simulate_burst(shape=shape, n_frames=5, seed=4)
    assert moving_masks(still.frames.astype(np.float32), still.homographies, factor=2).mean() <= 0.02


def test_coarse_shift_of_a_large_frame_is_measured_reduced():
    from gainfpn_cli.motion.track import COARSE_PIXELS, coarse_shift
    from gainfpn_cli.sim.scenes import procedural_scene

    scene = procedural_scene((1300, 1700), np.random.default_rng(0))
    ref = scene[40:1240, 40:1640]  # 1.9 MP: phase correlation runs halved
    assert ref.size > COARSE_PIXELS * 2
    moved = scene[40 + 13 : 1240 + 13, 40 - 37 : 1640 - 37]  # content moves by (+37, -13)
    np.testing.assert_allclose(coarse_shift(ref, moved), [37, -13], atol=0.5)


def _worst_field(burst, result):
    """Worst frame's RMS trajectory error (px) of any warp against the simulator's exact positions,
    over the pixels the moving object never covers."""
    ys, xs = np.mgrid[0 : SHAPE[0] : 4, 0 : SHAPE[1] : 4]
    points = np.stack([xs, ys], axis=-1).astype(np.float64)
    still = np.ones(xs.shape, bool) if burst.moving is None else ~burst.moving.any(axis=0)[::4, ::4]
    errors = [np.sum((result.warp.map_points(0, t, points) - burst.positions(t)[::4, ::4]) ** 2, axis=-1)[still]
              for t in range(1, len(burst.frames))]
    return max(float(np.sqrt(np.mean(e))) for e in errors)


@pytest.mark.parametrize(
    "shake, moving_object, expected",
    [(Shake(wobble_px=0.5), 0.0, "rolling"), (Shake(wobble_px=0.5), 0.1, "rolling"),
     (Shake(distortion_px=0.5), 0.0, "mesh")],
    ids=["wobble", "wobble+object", "distortion"],
)
def test_motion_no_single_warp_explains_gets_a_field_model(shake, moving_object, expected):
    # Seeds 3-10 (dead leaves, 200x260x6), worst frame: wobble 0.027-0.121 px,
    # with a 10 % object 0.029-0.101, distortion 0.045-0.092; the field model
    # was chosen every time. Held-out seed 11: 0.048, 0.061, 0.041 px. The
    # best single homography is off by several times more.
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=11, shake=shake, moving_object=moving_object,
                           scene="dead-leaves")
    frames = burst.frames.astype(np.float32)
    result = estimate_motion(frames)
    assert result.model == expected, result.reason
    assert _worst_field(burst, result) <= 0.1
    assert _worst_field(burst, estimate_motion(frames, model="homography")) > 3 * _worst_field(burst, result)


def test_field_models_are_not_chosen_for_a_plain_shake():
    # the global fits explain these points: the fields' extra parameters do not pay (GRIC)
    for seed in (11, 12):
        burst = simulate_burst(shape=SHAPE, n_frames=6, seed=seed, scene="dead-leaves")
        result = estimate_motion(burst.frames.astype(np.float32))
        assert result.model in ("translation", "affine", "homography"), result.reason
        assert {"rolling", "mesh"} <= set(result.per_frame[0].gric)


def _layer_errors(burst, result):
    """Worst frame's RMS trajectory error (px) and least traced fraction, off and on the object (each
    away from its edge by 3 px, where pixels mix both), and the largest fraction of the background off
    by more than 0.1 px."""
    import cv2

    from gainfpn_cli.geometry.warps import NOWHERE

    obj = burst.moving[0].astype(np.uint8)
    regions = (cv2.dilate(obj, np.ones((7, 7), np.uint8)) == 0, cv2.erode(obj, np.ones((7, 7), np.uint8)) > 0)
    ys, xs = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(np.float64)
    worst, traced, stray = [0.0, 0.0], [1.0, 1.0], 0.0
    for t in range(1, len(burst.frames)):
        est = result.warp.map_points(0, t, np.stack([xs, ys], axis=-1))
        truth = np.where(obj[..., None] > 0, burst.object_positions(t), burst.positions(t))
        inside = np.all((truth > 4) & (truth < [SHAPE[1] - 5, SHAPE[0] - 5]), axis=-1)
        err = np.linalg.norm(est - truth, axis=-1)
        has = est[..., 0] != NOWHERE
        for i, region in enumerate(regions):
            sel = region & inside
            worst[i] = max(worst[i], float(np.sqrt(np.mean(err[sel & has] ** 2))))
            traced[i] = min(traced[i], float((sel & has).sum() / sel.sum()))
        stray = max(stray, float((err[regions[0] & inside & has] > 0.1).mean()))
    return worst, traced, stray


@pytest.mark.parametrize("parallax", [0.0, 1.0], ids=["own-motion", "parallax"])
@pytest.mark.parametrize("scene", ["dead-leaves", "procedural"])
def test_layers_follow_an_object_that_moves_apart(scene, parallax):
    # issue 4: dense motion where one warp does not explain the scene. An object over 10 % of the frame
    # moves on its own, or is a nearer plane (parallax 1.0: displaced twice as far as the background).
    # Measured over seeds 3-10 (seed 11 held out), worst frame of 6: background 0.009-0.16 px on dead
    # leaves (0.05 px or less in 12 of 16 bursts); on the smooth procedural scene 0.03-0.41 px, from flat
    # background by the object's edge that takes its layer (0-0.8 % of the background off by > 0.1 px;
    # 3.1 and 11 % in two bursts whose background motion itself was off by 0.1-0.2 px); the object 0.05 px
    # or less in 24 of 32 bursts (0.053-0.48 px in the rest), 16-95 % of its pixels traced (the rest
    # hidden in some frame, or by its edge).
    burst = simulate_burst(shape=SHAPE, n_frames=6, seed=11, moving_object=0.1, parallax=parallax, scene=scene)
    result = estimate_motion(burst.frames.astype(np.float32))
    assert result.model == "layers" and len(result.layers) == 1, result.reason
    (background, on_object), traced, stray = _layer_errors(burst, result)
    assert on_object <= 0.05 and traced[1] >= 0.8
    assert traced[0] >= 0.9
    if scene == "dead-leaves":
        assert background <= 0.05
    else:
        assert stray <= 0.01


def test_a_forced_simpler_model_reports_the_motion_it_leaves_out():
    # misfit_px: the forced model's RMS distance from the homography fitted to the same points.
    # Measured 0.002-0.047 px where the forced model is the true one, 0.67-4.7 px for a
    # translation on bursts rotating 0.3-1 degree (pipeline.MAX_MISFIT_PX = 0.1 between them)
    from gainfpn_cli.pipeline import MAX_MISFIT_PX

    def worst_misfit(shake, model):
        burst = simulate_burst(shape=SHAPE, n_frames=5, seed=4, shake=shake)
        return max(f.misfit_px for f in estimate_motion(burst.frames.astype(np.float32), model=model).per_frame)

    assert worst_misfit(Shake(rotation_deg=0.0), "translation") < MAX_MISFIT_PX / 3
    assert worst_misfit(Shake(rotation_deg=1.0), "translation") > 3 * MAX_MISFIT_PX
    assert worst_misfit(Shake(rotation_deg=1.0), "affine") < MAX_MISFIT_PX  # a rotation is affine: 0.047 px
    frames = simulate_burst(shape=SHAPE, n_frames=4, seed=4).frames.astype(np.float32)
    assert all(f.misfit_px is None for f in estimate_motion(frames, model="homography").per_frame)
