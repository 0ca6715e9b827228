"""preview.png: what it shows of a map (subsampling, unestimated pixels) on mono, RGB and CFA maps."""

import dataclasses

import cv2
import numpy as np
import pytest

from gainfpn_cli.preview import PREVIEW_PX, UNESTIMATED, shown, write_preview
from gainfpn_cli.report import Holdout, Motion, PlaneReport, Prnu, Report
from gainfpn_cli.solve.result import AccurateStats

REPORT = Report(motion=Motion("affine"), inputs=("a", "b", "c", "d"),
                planes={"Y": PlaneReport("accurate", "Y", AccurateStats(1, (10,), 0, 0, 0.8), "pixel")},
                prnu_percent=Prnu.of({"pixel": 4.9, "column": 1.0, "row": 0.1}), predicted_residual_percent=0.5,
                holdout=Holdout("d", 0.2, True))


def test_a_large_map_is_shown_on_every_nth_pixel_not_averaged():
    rng = np.random.default_rng(0)
    k = (1 + 0.01 * rng.standard_normal((2100, 3000, 1))).astype(np.float32)
    conf = rng.uniform(0, 1, k.shape).astype(np.float32)
    deviation, c, step = shown(k, conf)
    assert step == 3 and max(deviation.shape) <= PREVIEW_PX
    np.testing.assert_array_equal(deviation, 100.0 * (k[::3, ::3, 0].astype(np.float64) - 1.0))
    np.testing.assert_array_equal(c, conf[::3, ::3, 0])
    assert shown(k[:1000, :1024], conf[:1000, :1024])[2] == 1


@pytest.mark.parametrize("cfa, channels", [(None, ("Y",)), ("RGGB", ("raw",)), (None, ("R", "G", "B"))])
def test_maps_of_every_kind_are_drawn_with_unestimated_pixels_in_the_legend_colour(tmp_path, cfa, channels):
    rng = np.random.default_rng(1)
    k = (1 + 0.02 * rng.standard_normal((120, 160, 1 if cfa or len(channels) == 1 else 3))).astype(np.float32)
    conf = np.full_like(k, 0.8)
    k[:40], conf[:40] = 1.0, 0.0  # the top third unestimated
    write_preview(tmp_path / "p.png", k, conf, report=REPORT, name="burst/", cfa=cfa, channels=channels)
    image = cv2.imread(str(tmp_path / "p.png"))[..., ::-1]  # RGB
    grey = np.array([int(UNESTIMATED[i:i + 2], 16) for i in (1, 3, 5)])
    assert (np.abs(image - grey).sum(axis=2) == 0).sum() > 2 * 40 * 160  # both maps' top thirds (and the legend)


def test_a_rejected_estimate_draws_a_flat_map(tmp_path):
    k = np.ones((64, 80, 1), np.float32)
    report = dataclasses.replace(REPORT, predicted_residual_percent=None, holdout=Holdout("d", 1.3, False),
                                 prnu_percent=Prnu())
    write_preview(tmp_path / "p.png", k, np.zeros_like(k), report=report, name="b/")
    assert cv2.imread(str(tmp_path / "p.png")) is not None
