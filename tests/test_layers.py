import numpy as np
import pytest

from gainfpn_cli.geometry.warps import apply_homography
from gainfpn_cli.motion.layers import MEMBER_PX, find_layers


def _homography(dx, dy, angle_deg=0.0, about=(0.0, 0.0)):
    a = np.deg2rad(angle_deg)
    c = np.array([[1.0, 0, about[0]], [0, 1.0, about[1]], [0, 0, 1.0]])
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    T = np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])
    return T @ c @ R @ np.linalg.inv(c)


def _points(rng, n_frames=6, n=400, n_object=60, n_wild=20, object_motion="shift"):
    """Points of a background moving by ``base``, an object in a disk moving on its own, and wild tracks."""
    src = rng.uniform([0, 0], [320, 240], (n, 2))
    on_object = np.zeros(n, bool)
    centre = np.array([200.0, 120.0])
    on_object[np.argsort(np.linalg.norm(src - centre, axis=1))[:n_object]] = True
    base = np.array([np.eye(3)] + [_homography(*rng.normal(0, 2, 2), rng.normal(0, 0.3)) for _ in range(n_frames - 1)])
    dst = np.empty((n_frames - 1, n, 2))
    truth = [np.eye(3)]
    for t in range(1, n_frames):
        if object_motion == "shift":
            own = _homography(2.0 * t, -1.0 * t)
        else:  # spinning about its centre: no shift of the background's motion explains it
            own = _homography(1.0 * t, 0.5 * t, angle_deg=1.5 * t, about=centre)
        truth.append(base[t] @ own)
        dst[t - 1] = np.where(on_object[:, None], apply_homography(truth[t], src), apply_homography(base[t], src))
    dst += rng.normal(0, 0.02, dst.shape)
    wild = rng.choice(np.flatnonzero(~on_object), n_wild, replace=False)
    dst[:, wild] += rng.uniform(-8, 8, (n_frames - 1, n_wild, 2))
    lost = rng.random(dst.shape[:2]) < 0.05
    dst[lost] = np.nan
    return src, dst, base, on_object, np.array(truth)


@pytest.mark.parametrize("motion, model", [("shift", "shift"), ("spin", "homography")])
def test_the_points_of_an_object_with_its_own_motion_form_a_layer(motion, model):
    rng = np.random.default_rng(1)
    src, dst, base, on_object, truth = _points(rng, object_motion=motion)
    layers = find_layers(src, dst, base)
    assert layers.n_layers == 2 and layers.models == [model]
    # no background point or wild track joins; object points do, but for a few the background's motion
    # explains to within OUTLIER_PX (near the centre the object spins about)
    assert not (layers.members[~on_object]).any()
    assert (layers.members[on_object] == 1).mean() >= (1.0 if motion == "shift" else 0.95)
    for t in range(1, len(base)):
        moved = apply_homography(layers.homographies[t, 1], src[on_object])
        assert np.sqrt(np.mean(np.sum((moved - apply_homography(truth[t], src[on_object])) ** 2, 1))) < 0.02
    np.testing.assert_array_equal(layers.homographies[:, 0], base)


def test_wild_tracks_do_not_make_a_layer():
    # 40 of 400 points (10 %) tracked wrongly, each its own way: no layer
    rng = np.random.default_rng(2)
    src, dst, base, _, _ = _points(rng, n_object=0, n_wild=40)
    layers = find_layers(src, dst, base)
    assert layers.n_layers == 1 and not layers.members.any()


def test_a_layer_needs_enough_points():
    rng = np.random.default_rng(3)
    src, dst, base, on_object, _ = _points(rng, n_object=11)  # fewer than MIN_POINTS
    assert find_layers(src, dst, base).n_layers == 1
    src, dst, base, on_object, _ = _points(rng, n_object=14)
    layers = find_layers(src, dst, base)
    assert layers.n_layers == 2 and (layers.members == 1).sum() == 14
    assert np.nanmax(layers.residuals[:, on_object]) < MEMBER_PX


def test_tracks_that_stay_still_on_the_sensor_are_not_a_layer():
    # corners of a flat area are the gain pattern's: tracked, they stay where they are while the scene
    # moves. They agree with each other like a surface would, but say nothing about the gain.
    rng = np.random.default_rng(4)
    src, dst, base, on_object, _ = _points(rng, n_wild=0)
    dst[:, on_object] = src[on_object] + rng.normal(0, 0.02, (len(dst), on_object.sum(), 2))
    assert all(np.median(np.linalg.norm(apply_homography(H, src) - src, axis=1)) > 1 for H in base[1:])
    layers = find_layers(src, dst, base)
    assert layers.n_layers == 1 and not layers.members.any()
