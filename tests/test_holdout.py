"""The hold-out check: unbiased by the fit's noise, significant against its own noise, plane by plane."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gainfpn_cli import api, checking, solving
from gainfpn_cli.geometry.planes import solve_grids
from gainfpn_cli.geometry.warps import GlobalWarp, LayeredWarp
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.solve.holdout import BLOCK, Check, _jackknife, column_strips, holdout_checks

MONO12 = dataclasses.replace(PRESETS["raw12"], cfa=None, fpn_pixel=0.02)


def test_jackknife_standard_error_is_the_spread_of_the_ratio():
    # blocks of a residual ratio near 0.95: the jackknife's error of one draw against the spread of 400 draws
    rng = np.random.default_rng(0)

    def draw():
        den = rng.gamma(20.0, 1.0, 300)
        return den * rng.normal(0.95, 0.1, 300), den

    ratios = [_jackknife(*draw()).ratio for _ in range(400)]
    errors = [_jackknife(*draw()).standard_error for _ in range(50)]
    assert np.mean(errors) == pytest.approx(np.std(ratios), rel=0.15)


def test_a_map_whose_error_runs_down_columns_is_jackknifed_by_columns():
    # 16 x 16 blocks whose ratio has a part shared down each column of blocks (a column model's error)
    # four times the blocks' own: the blocks' jackknife takes them for 256 independent draws and its
    # standard error is about a quarter of the spread of the ratio; leaving out whole columns is not
    rng = np.random.default_rng(1)
    columns = np.tile(np.arange(16), 16)

    def draw():
        den = rng.gamma(20.0, 1.0, 256)
        return den * (0.97 + rng.normal(0, 0.02, 16)[columns] + rng.normal(0, 0.005, 256)), den

    ratios = [_jackknife(*draw()).ratio for _ in range(400)]
    blocks = [_jackknife(*draw()).standard_error for _ in range(100)]
    by_columns = [_jackknife(*draw(), columns).standard_error for _ in range(100)]
    assert np.mean(by_columns) == pytest.approx(np.std(ratios), rel=0.15)
    assert np.mean(blocks) < 0.4 * np.std(ratios)
    num, den = draw()  # each block its own group: the blocks' jackknife
    assert _jackknife(num, den, np.arange(256)).standard_error == pytest.approx(_jackknife(num, den).standard_error)
    assert _jackknife(num, den, np.zeros(256)).standard_error == np.inf  # one column: nothing to leave out


def test_column_strips_follow_the_frames_columns_on_every_grid():
    grids = {g.name: g for g in solve_grids("RGGB", ("Y",), (160, 192), greens_together=True)}
    red = grids["R@00"]  # 80 x 96: 5 x 6 blocks, a strip each column of them
    assert np.array_equal(column_strips(red, red.shape), np.tile(np.arange(6), 5))
    greens = grids["G"]  # the lattice is rotated: a strip holds blocks of several of its rows and columns
    column = column_strips(greens, greens.shape)
    h, w = greens.shape
    y, x = np.meshgrid(np.arange(0, h, BLOCK) + BLOCK / 2, np.arange(0, w, BLOCK) + BLOCK / 2, indexing="ij")
    frame_x = np.asarray(greens.S)[0] @ np.stack([x.ravel(), y.ravel(), np.ones(x.size)])
    assert np.all(np.diff(column[np.argsort(frame_x)]) >= 0)  # ordered as the frame's x
    side = BLOCK * np.sqrt(2)  # a lattice block's side in frame px
    assert all(np.ptp(frame_x[column == c]) < side for c in np.unique(column))
    assert len(np.unique(column)) >= np.ptp(frame_x) / side


def test_a_correction_is_kept_only_below_one_by_z_standard_errors():
    assert Check(0.95, 0.02, np.ones(2), np.ones(2)).passed(2.0)
    assert not Check(0.97, 0.02, np.ones(2), np.ones(2)).passed(2.0)
    assert not Check(1.0, float("inf"), np.ones(1), np.ones(1)).passed(2.0)


def test_the_check_does_not_see_the_noise_the_fit_learned():
    # a dark 12-bit burst: the accurate solver's k learns ~1/7 of the reference's noise, so comparing the
    # held-out frame with the reference under the written k flatters it; the check must agree with two
    # frames not fitted (the scene solver, which auto takes for this aliased burst, learns less of it)
    b = simulate_burst(shape=(240, 320), n_frames=9, sensor=MONO12, exposure=0.1, scene="dead-leaves", seed=3)
    frames = b.frames.astype(np.float32) - MONO12.black_level
    result = api.estimate(frames[:8], saturation=MONO12.white_level - MONO12.black_level,
                          **{"solver.workers": 1, "solver.method": "accurate"})
    assert result.report.status == "accepted"  # (ratio 0.91 +- 0.01 when written)
    grids = list(solve_grids(None, ("Y",), frames.shape[1:], greens_together=True))
    k = result.k
    stack = frames[..., None]

    def ratio(pair):
        picked = stack[list(pair)]
        return holdout_checks(picked, None, np.ones(2), GlobalWarp(b.homographies[list(pair)]), k, grids=grids,
                              saturation=None)["Y"].ratio

    unfitted, flattering = ratio((8, 7)), ratio((0, 7))
    assert flattering < unfitted - 0.05  # the bias is real
    assert result.report.holdout.residual_ratio == pytest.approx(unfitted, abs=0.03)


def test_a_plane_the_check_rejects_is_written_as_k_1_and_the_others_are_kept(monkeypatch):
    # a solver that spoils the red plane (10 % random gains): only red falls back, with a warning
    b = simulate_burst(shape=(128, 160), n_frames=8, sensor=PRESETS["raw12"], exposure=0.5, seed=101)
    frames = b.frames.astype(np.float32) - PRESETS["raw12"].black_level
    solve = solving.solve_raw

    def spoil_red(*args, **kwargs):
        k, confidence, solved, hot = solve(*args, **kwargs)
        red = k[0::2, 0::2]
        red *= 1 + 0.1 * np.random.default_rng(0).standard_normal(red.shape).astype(np.float32)
        return k, confidence, solved, hot

    monkeypatch.setattr(solving, "solve_raw", spoil_red)
    saturation = PRESETS["raw12"].white_level - PRESETS["raw12"].black_level
    result = api.estimate(frames, cfa="RGGB", saturation=saturation, **{"solver.workers": 2})
    holdout = result.report.holdout
    assert holdout.planes["R@00"].residual_ratio > 1 and not holdout.planes["R@00"].passed
    assert holdout.planes["G"].passed and holdout.passed and result.report.status == "accepted"
    red, green = result.k[0::2, 0::2, 0], result.k[0::2, 1::2, 0]
    assert np.all(red == 1.0) and np.all(result.confidence[0::2, 0::2, 0] == 0.0)
    truth = 1.0 / b.gain[0::2, 1::2]
    assert np.corrcoef(green.ravel(), truth.ravel())[0, 1] > 0.5  # kept its correction: measured 0.63
    assert any("R@00" in w and "k = 1 (no correction) was written" in w for w in result.report.warnings)


def test_layers_left_without_the_reference_keep_its_labels():
    # the check fits without the reference: a layered motion must still ask the reference's labels
    rng = np.random.default_rng(5)
    layers = np.tile(np.eye(3), (3, 2, 1, 1))
    layers[:, :, 0, 2] = rng.normal(0, 2, (3, 2))
    labels = np.zeros((3, 40, 40), np.uint8)
    labels[:, 10:30, 10:30] = 1
    labels[0, 10:20, 10:30] = 0  # the reference sees less of layer 1
    warp = LayeredWarp(layers, labels, np.eye(3))
    points = np.stack(np.meshgrid(np.arange(40.0), np.arange(40.0)), axis=-1)
    np.testing.assert_array_equal(warp.select([1, 2]).map_points(0, 1, points), warp.map_points(1, 2, points))


def test_blocks_where_the_checks_own_fit_went_wrong_are_left_out():
    # the check's k off by 1 % from the written (true) gains, and by 30 % in one 32 px square (4 blocks):
    # those blocks judge the check's own fit, not the written map; 30 % everywhere is judged as it is
    b = simulate_burst(shape=(96, 128), n_frames=3, seed=8)
    frames = b.frames.astype(np.float32)[[0, 2], ..., None]
    grids = list(solve_grids(None, ("Y",), frames.shape[1:], greens_together=True))
    written = (1.0 / b.gain)[..., None].astype(np.float32)
    rng = np.random.default_rng(1)
    small, noise = (s * rng.standard_normal(written.shape).astype(np.float32) for s in (0.01, 0.3))
    patch = np.zeros(written.shape, bool)
    patch[32:64, 64:96] = True

    def check(k, disagreement=None):
        return holdout_checks(frames, None, np.ones(2), GlobalWarp(b.homographies[[0, 2]]), k, grids=grids,
                              saturation=None, disagreement=disagreement)["Y"]

    spoiled = written * (1 + small + np.where(patch, noise, 0))
    assert not check(spoiled).passed(2.0)  # the square alone rejects a map that is right elsewhere
    kept = check(spoiled, (spoiled - written) ** 2)
    assert kept.left_out == 4 and kept.passed(2.0) and kept.ratio < 0.5
    everywhere = written * (1 + noise)
    judged = check(everywhere, (everywhere - written) ** 2)
    assert judged.left_out == 0 and not judged.passed(2.0)


def _plane_errors(result, burst):
    """Per CFA plane of the written map: (estimated?, the gain FPN left on its estimated photosites, the
    FPN they had), in %."""
    out = {}
    for name, (y, x) in {"R": (0, 0), "G1": (0, 1), "G2": (1, 0), "B": (1, 1)}.items():
        est = result.confidence[y::2, x::2, 0] > 0
        if not est.any():
            out[name] = (False, 0.0, 0.0)
            continue
        gain = burst.gain[y::2, x::2][est]
        left = result.k[y::2, x::2, 0][est] * gain
        out[name] = (True, 100 * np.std(left / left.mean()), 100 * np.std(gain / gain.mean()))
    return out


@pytest.mark.parametrize("shape, seed", [((240, 320), 2),
                                         pytest.param((480, 640), 3, marks=pytest.mark.slow)])
def test_a_plane_that_learned_the_aliasing_every_pair_shares_is_not_kept(shape, seed):
    # 12-bit RGGB dead leaves: a red or blue plane sampled every other photosite is aliased, and k fitted to the
    # other frames learns part of the interpolation error the held-out pair makes too, so the raw residual of
    # that pair falls (measured without the low-pass: red 0.993 +- 0.003 at 240x320 seed 2, blue 0.992 +- 0.004
    # at 640x480 seed 3, both kept, the latter with its gain FPN 0.99 -> 1.70 %). No plane written may be
    # farther from the truth than no correction. (640x480 seed 3 kept its blue plane at 1.045 % from 0.995 %
    # through a column model the aliasing made, until the column gate and the pixel FPN pooled over parts
    # of 1000 px: docs/limits.md, "The hold-out check".)
    b = simulate_burst(shape=shape, n_frames=8, sensor=PRESETS["raw12"], exposure=0.75, scene="dead-leaves",
                       seed=seed)
    frames = b.frames.astype(np.float32) - PRESETS["raw12"].black_level
    result = api.estimate(frames, cfa="RGGB", saturation=PRESETS["raw12"].white_level - PRESETS["raw12"].black_level)
    for name, (kept, left, had) in _plane_errors(result, b).items():
        assert not kept or left < had, (name, left, had)


@pytest.mark.parametrize("seed, exposure, first_ratio_below_1", [(9, 0.3, True), (3, 0.08, False)])
def test_a_check_too_small_to_decide_looks_again_on_a_region_twice_as_wide(monkeypatch, seed, exposure,
                                                                          first_ratio_below_1):
    # dark 12-bit 128x160 bursts: on the central 48 px seed 9's check is below 1 but not by 2 standard
    # errors (0.913 +- 0.048), on 96 px it is (0.909 +- 0.028). A first look above 1 (seed 3 at 8 %
    # exposure: 1.005 +- 0.020) is not looked at again. (Of seeds 0-39 at 30 % exposure, 5 are undecided
    # on 48 px and none reads above 1.)
    b = simulate_burst(shape=(128, 160), n_frames=7, sensor=MONO12, exposure=exposure, scene="dead-leaves",
                       seed=seed)
    frames = b.frames.astype(np.float32) - MONO12.black_level
    monkeypatch.setattr(solving, "CHECK_SIDE", 48)

    def plane(wider):
        monkeypatch.setattr(checking, "WIDER", wider)
        result = api.estimate(frames, saturation=MONO12.white_level - MONO12.black_level,
                              **{"solver.workers": 1, "solver.method": "accurate"})
        return result.report.holdout.planes["Y"]

    once, twice = plane(1), plane(2)
    assert not once.passed and once.region_px == 48
    if first_ratio_below_1:
        assert once.residual_ratio < 1
        assert twice.passed and twice.region_px == 96 and twice.standard_error < once.standard_error
    else:
        assert once.residual_ratio > 1 and twice == once
