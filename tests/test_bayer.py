import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gainfpn_cli import bayer


@given(hnp.arrays(np.float32, hnp.array_shapes(min_dims=2, max_dims=2, min_side=2, max_side=15)))
def test_split_merge_round_trip(mosaic):
    planes = bayer.split_planes(mosaic)
    assert sum(p.size for p in planes) == mosaic.size
    np.testing.assert_array_equal(bayer.merge_planes(planes, mosaic.shape), mosaic)


def test_split_returns_copies():
    mosaic = np.arange(16.0).reshape(4, 4)
    planes = bayer.split_planes(mosaic)
    planes[0][...] = -1
    assert mosaic.min() == 0


def test_merge_checks_shapes():
    with pytest.raises(ValueError, match="offset"):
        bayer.merge_planes([np.zeros((2, 2))] * 4, (5, 4))


def test_colour_groups_and_index_map():
    assert bayer.colour_groups("RGGB") == {"R": [0], "G": [1, 2], "B": [3]}
    idx = bayer.colour_index_map("GRBG", (3, 5))  # colours sorted: B=0, G=1, R=2
    np.testing.assert_array_equal(idx, [[1, 2, 1, 2, 1], [0, 1, 0, 1, 0], [1, 2, 1, 2, 1]])


def test_grey_proxy_averages_cells():
    mosaic = np.arange(20.0).reshape(4, 5)
    proxy = bayer.grey_proxy(mosaic)
    assert proxy.shape == (2, 2)
    assert proxy[1, 1] == np.mean([12, 13, 17, 18])


@given(st.floats(-20, 20), st.floats(-20, 20), st.sampled_from(bayer.OFFSETS))
def test_plane_homography_agrees_with_mosaic_motion(tx, ty, offset):
    # a point of a plane, taken to the mosaic, moved, and brought back must
    # equal the point moved by the conjugated homography
    H = np.array([[1.0, 0.001, tx], [-0.001, 1.0, ty], [1e-6, 0.0, 1.0]])
    S = bayer.plane_to_mosaic(offset)
    H_plane = np.linalg.inv(S) @ H @ S
    u = np.array([7.0, 3.0, 1.0])
    mosaic_point = S @ u
    moved = H @ mosaic_point
    expected = np.linalg.inv(S) @ (moved / moved[2])
    got = H_plane @ u
    np.testing.assert_allclose(got / got[2], expected / expected[2], rtol=0, atol=1e-9)
    # for a pure translation, the plane moves by half as much
    T = np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose((np.linalg.inv(S) @ T @ S)[:2, 2], [tx / 2, ty / 2], atol=1e-12)
