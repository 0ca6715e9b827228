import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli.geometry.resample import positions, sample
from gainfpn_cli.geometry.warps import FieldWarp, GlobalWarp, as_warp, field_at
from gainfpn_cli.motion.fields import FIELD_CELLS, fit_field

SHAPE = (240, 320)


def _homography(tx, ty, angle_deg=0.0, persp=0.0):
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    H = np.array([[c, -s, tx], [s, c, ty], [persp, -persp, 1.0]])
    return H


@functools.lru_cache(maxsize=None)
def _field_warp(model: str, amplitude: float, seed: int = 0) -> FieldWarp:
    """Two frames besides the reference, each with a field as rough as the model is meant to follow:
    a rolling wobble of 3 periods down the rows, or a mesh wave of 1.5 periods across the frame."""
    from gainfpn_cli.motion.fields import design

    rng = np.random.default_rng(seed)
    cells = FIELD_CELLS[model]
    ys, xs = np.mgrid[0 : SHAPE[0] : 2, 0 : SHAPE[1] : 2].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    a = design(pts, SHAPE, cells)
    periods = (3.0, 0.0) if model == "rolling" else (1.5, 1.5)
    ny, nx = cells[0] + 3, (1 if cells[1] == 0 else cells[1] + 3)
    coefficients = np.zeros((3, 2, ny, nx))
    for t in (1, 2):
        for axis, share in ((0, 1.0), (1, 0.3)):
            phase = 2 * np.pi * (periods[0] * pts[:, 1] / SHAPE[0] + periods[1] * pts[:, 0] / SHAPE[1])
            wave = share * amplitude * np.sin(phase + rng.uniform(0, 2 * np.pi))
            coefficients[t, axis] = np.linalg.lstsq(a, wave, rcond=None)[0].reshape(ny, nx)
    H = np.stack([np.eye(3), _homography(2.5, -1.5, 0.3, 1e-5), _homography(-3.0, 2.0, -0.2)])
    return FieldWarp(H, coefficients, SHAPE)


def _points(n=200, seed=1):
    rng = np.random.default_rng(seed)
    return rng.uniform([0, 0], [SHAPE[1] - 1, SHAPE[0] - 1], (n, 2))


@pytest.mark.parametrize("model", ["rolling", "mesh"])
def test_field_warp_maps_are_inverse_and_satisfy_the_model(model):
    warp = _field_warp(model, 1.5)
    p = _points()
    for t in (1, 2):
        q = warp.map_points(0, t, p)
        # the defining equation: q = H_t p + r_t(q)
        H = warp.homographies[t]
        hp = np.c_[p, np.ones(len(p))] @ H.T
        np.testing.assert_allclose(q, hp[:, :2] / hp[:, 2:] + warp.field(t, q), atol=1e-6)
        np.testing.assert_allclose(warp.map_points(t, 0, q), p, atol=1e-6)
        # frame to frame goes through the reference
        np.testing.assert_allclose(warp.map_points(1, 2, warp.map_points(0, 1, p)), warp.map_points(0, 2, p), atol=1e-6)


@pytest.mark.parametrize("model", ["rolling", "mesh"])
def test_pair_map_lattice_is_within_a_fraction_of_the_resamplers_rounding(model):
    warp = _field_warp(model, 1.5)
    region = (10, 20, 50, 70)  # y0, x0, h, w
    M = warp.pair(2, 1, region)
    ys, xs = np.mgrid[10:60, 20:90].astype(np.float64)
    exact = warp.map_points(2, 1, np.stack([xs, ys], axis=-1)) - [20, 10]
    assert M.shape == (50, 70, 2) and M.dtype == np.float32
    error = np.abs(M - exact)
    # OpenCV rounds sample positions to 1/32 px; the lattice adds far less
    assert error.max() < 0.005 and np.median(error) < 2e-4
    whole = warp.pair(2, 1, (0, 0) + SHAPE)  # across the frame's border too
    ys, xs = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(np.float64)
    assert np.abs(whole - warp.map_points(2, 1, np.stack([xs, ys], axis=-1))).max() < 0.005
    small = warp.pair(2, 1, (0, 0, 8, 5))  # smaller than two lattice steps: exact
    np.testing.assert_allclose(small, warp.map_points(2, 1, np.stack(np.meshgrid(np.arange(5.0), np.arange(8.0)), -1)),
                               atol=1e-4)


@settings(max_examples=20, deadline=None)
@given(st.floats(0.5, 3.0), st.floats(-4.0, 4.0), st.floats(-4.0, 4.0))
def test_conjugate_speaks_other_pixels_for_both_kinds(scale, ox, oy):
    # c -> S c maps new pixels to old ones; maps in new pixels are S^-1 (old map) S
    S = np.array([[scale, 0, ox], [0, scale, oy], [0, 0, 1.0]])
    p = _points(30)
    new = np.c_[p, np.ones(len(p))] @ np.linalg.inv(S).T
    new = new[:, :2]
    for warp in (_field_warp("mesh", 0.5), GlobalWarp(_field_warp("mesh", 0.5).homographies)):
        old = warp.map_points(0, 1, p)
        mapped = warp.conjugate(S).map_points(0, 1, new)
        back = np.c_[mapped, np.ones(len(p))] @ S.T
        np.testing.assert_allclose(back[:, :2], old, atol=1e-6)


def test_global_pair_is_the_region_shifted_homography_and_resamples_like_a_map():
    H = np.stack([np.eye(3), _homography(1.3, -0.7, 0.4, 2e-5)])
    warp = GlobalWarp(H)
    M = warp.pair(0, 1, (5, 7, 40, 60))
    shift = np.array([[1.0, 0, 7], [0, 1.0, 5], [0, 0, 1.0]])
    np.testing.assert_allclose(M, np.linalg.inv(shift) @ H[1] @ shift)
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 100, (60, 80)).astype(np.float32)
    by_matrix = sample(image, M, (40, 60), kernel="cubic")
    by_map = sample(image, positions(M, (40, 60)).astype(np.float32), (40, 60), kernel="cubic")
    # both quantise positions to 1/32 px; on white noise that differs by a few percent of its spread
    assert np.sqrt(np.mean((by_matrix - by_map)[4:-4, 4:-4] ** 2)) < 0.05 * image.std()
    with pytest.raises(ValueError, match="map of shape"):
        sample(image, np.zeros((3, 4, 2), np.float32), (40, 60))


def test_as_warp():
    H = np.stack([np.eye(3)] * 2)
    assert isinstance(as_warp(H), GlobalWarp)
    warp = _field_warp("rolling", 0.1)
    assert as_warp(warp) is warp
    with pytest.raises(ValueError, match="finite"):
        as_warp(np.full((2, 3, 3), np.inf))
    assert warp.select([0, 2]).n_frames == 2


@pytest.mark.parametrize("model", ["rolling", "mesh"])
def test_fit_field_recovers_a_field_and_ignores_a_moving_cluster(model):
    warp = _field_warp(model, 0.6, seed=3)
    src = _points(600, seed=4)
    dst = warp.map_points(0, 1, src) + np.random.default_rng(5).normal(0, 0.02, (600, 2))
    # a moving object: a cluster of points 3 px off
    cluster = np.linalg.norm(src - [40, 30], axis=1) < 15
    dst[cluster] += [3.0, -2.0]
    start = np.eye(3)
    start[:2, 2] = np.median(dst - src, axis=0)
    fit = fit_field(src, dst, start, SHAPE, model)
    assert not fit.keep[cluster].any() and fit.keep[~cluster].mean() > 0.97
    check = _points(300, seed=6)
    got = np.c_[check, np.ones(len(check))] @ fit.H.T
    got = got[:, :2] / got[:, 2:]
    truth = warp.map_points(0, 1, check)
    # q = H p + r(q): evaluate the fitted model at the true q. Measured RMS
    # (points 0.02 px exact): rolling 0.005 px; mesh 0.017 px inside, 0.05 px
    # within 16 px of the edges, where the ridge pulls coefficients few points
    # constrain toward 0 (fieldfit.RIDGE)
    error = np.linalg.norm(got + field_at(fit.coefficients, truth, SHAPE) - truth, axis=1)
    inside = np.all((check > 16) & (check < np.array(SHAPE[::-1]) - 17), axis=1)
    assert np.sqrt(np.mean(error[inside] ** 2)) < 0.025
    assert np.sqrt(np.mean(error**2)) < 0.04
    assert 8 < fit.dof < 8 + 2 * fit.coefficients[0].size


def _two_layers():
    """A background moving (+2, 0) and a block x >= 39.5 of a 60x80 frame moving (-3, +1) in frame 1,
    over the background; labelled on a grid of half the frame's resolution."""
    from gainfpn_cli.geometry.warps import NO_LAYER, LayeredWarp

    shift = lambda dx, dy: np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])  # noqa: E731
    layers = np.array([[np.eye(3), np.eye(3)], [shift(2, 0), shift(-3, 1)]])
    half = np.array([[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1.0]])  # frame pixel -> half-resolution pixel
    labels = np.zeros((2, 30, 40), np.uint8)
    labels[0][:, 20:] = 1  # the reference: the block from x = 39.5 (label pixel 20)
    labels[1][:, 18:] = 1  # frame 1: from x = 36.5, hiding the background the reference sees at 34.5 .. 39.5
    labels[1][:, 5] = NO_LAYER  # say frame 1 sees something no layer explains at x = 9.5 .. 11.5
    return LayeredWarp(layers, labels, half)


def test_a_layered_warp_moves_each_pixel_with_its_layer_and_occluded_ones_nowhere():
    from gainfpn_cli.geometry.warps import NOWHERE

    warp = _two_layers()
    moved = warp.map_points(0, 1, np.array([[20.0, 7.0], [50.0, 7.0], [37.0, 7.0], [8.0, 7.0]]))
    np.testing.assert_array_equal(moved[:2], [[22.0, 7.0], [47.0, 8.0]])
    # the background at 37 goes to 39, behind the block in frame 1; at 8 to 10, which no layer explains
    assert np.all(moved[2:] == NOWHERE)
    np.testing.assert_array_equal(warp.map_points(1, 0, np.array([[22.0, 7.0], [47.0, 8.0]])),
                                  [[20.0, 7.0], [50.0, 7.0]])
    assert np.all(warp.map_points(1, 0, np.array([[10.0, 7.0]])) == NOWHERE)
    np.testing.assert_array_equal(warp.homographies, warp.layers[:, 0])


def test_a_layered_warp_pair_conjugate_and_select_agree_with_its_points():
    from gainfpn_cli.geometry.warps import NOWHERE

    warp = _two_layers()
    region = (3, 30, 5, 20)  # (y0, x0, h, w)
    M = warp.pair(0, 1, region)
    ys, xs = np.mgrid[3:8, 30:50].astype(np.float64)
    expected = warp.map_points(0, 1, np.stack([xs, ys], axis=-1))
    traced = expected[..., 0] != NOWHERE
    np.testing.assert_allclose(M[traced], (expected - [30, 3])[traced], atol=1e-5)
    assert np.all(M[~traced] == NOWHERE) and traced.any() and (~traced).any()
    S = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1.0]])  # a coarser grid c with S c = frame pixels
    c = np.array([[4.75, 3.25], [24.75, 3.25]])
    np.testing.assert_allclose(warp.conjugate(S).map_points(0, 1, c),
                               (warp.map_points(0, 1, c * 2 + 0.5) - 0.5) / 2)
    assert warp.select([0]).n_frames == 1 and warp.select([1, 0]).labels[0][0, 5] != 0


def test_bounded_maps_sample_alike_where_the_samples_are_valid():
    # NOWHERE positions are brought to just outside the source (OpenCV's
    # reflecting border walked to -1e5 one reflection at a time: a layered
    # solve of 120x160x6 took 4.5 s, now 0.4 s, with the same k)
    from gainfpn_cli.geometry.resample import bounded, sample, valid_samples
    from gainfpn_cli.geometry.warps import NOWHERE

    rng = np.random.default_rng(0)
    image = rng.uniform(1, 2, (30, 40)).astype(np.float32)
    ys, xs = np.mgrid[0:30, 0:40].astype(np.float32)
    M = np.stack([xs + 0.3, ys - 0.6], axis=-1)
    M[rng.uniform(size=(30, 40)) < 0.2] = NOWHERE
    M[0, 0] = [55.0, 12.0]  # past the right edge, legitimately
    B = bounded(M, image.shape)
    assert B.min() >= -8 and B[..., 0].max() <= 39 + 8 and B[..., 1].max() <= 29 + 8
    valid = valid_samples(np.ones(image.shape, bool), M, image.shape, kernel="lanczos4")
    np.testing.assert_array_equal(valid, valid_samples(np.ones(image.shape, bool), B, image.shape, kernel="lanczos4"))
    np.testing.assert_array_equal(sample(image, B, image.shape)[valid], sample(image, M, image.shape)[valid])
    assert valid.any() and not valid[0, 0]
    H = np.eye(3)
    assert bounded(H, image.shape) is H
