import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gainfpn_cli.geometry import cfa as bayer
from gainfpn_cli.geometry.planes import solve_grids


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


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("shape", [(6, 8), (7, 9), (10, 5)])
def test_green_lattice_maps_every_green_photosite_exactly(cfa, shape):
    from gainfpn_cli.geometry.cfa import green_lattice

    lattice = green_lattice(cfa, shape)
    colours = np.array(list(cfa)).reshape(2, 2)
    is_green = np.tile(colours, (shape[0] // 2 + 1, shape[1] // 2 + 1))[: shape[0], : shape[1]] == "G"
    np.testing.assert_array_equal(is_green[lattice.rows, lattice.cols], True)
    assert len(lattice.rows) == is_green.sum()
    # S takes each green's grid position to its mosaic position
    mapped = lattice.S @ np.stack([lattice.u, lattice.v, np.ones_like(lattice.u)])
    np.testing.assert_array_equal(mapped[:2], np.stack([lattice.cols, lattice.rows]))
    # distinct cells, and gather/scatter are inverse on the greens
    assert len(set(zip(lattice.v, lattice.u))) == len(lattice.u)
    mosaic = np.arange(shape[0] * shape[1], dtype=np.float32).reshape(shape) + 1
    back = np.zeros_like(mosaic)
    lattice.scatter(back, lattice.gather(mosaic))
    np.testing.assert_array_equal(back[is_green], mosaic[is_green])
    assert lattice.gather(mosaic).astype(bool).sum() == is_green.sum()
    # lattice neighbours are diagonal neighbours in the mosaic: pitch sqrt(2)
    step = lattice.S[:2, :2] @ np.array([1.0, 0.0])
    assert np.hypot(*step) == pytest.approx(np.sqrt(2))


def test_no_green_lattice_without_diagonal_greens():
    from gainfpn_cli.geometry.cfa import green_lattice

    assert green_lattice("RGBG", (8, 8)) is None  # greens side by side in one row
    assert green_lattice("RGBW", (8, 8)) is None


@pytest.mark.parametrize("cfa, channels", [("RGGB", ("Y",)), ("GRBG", ("Y",)), (None, ("R", "G", "B"))])
@pytest.mark.parametrize("greens_together", [True, False])
@pytest.mark.parametrize("shape", [(6, 8), (7, 9)])
def test_a_grid_knows_its_shape_without_gathering(cfa, channels, greens_together, shape):
    frame = np.zeros(shape + (len(channels),), np.float32)
    for grid in solve_grids(cfa, channels, shape, greens_together=greens_together):
        assert grid.shape == grid.gather(frame).shape
