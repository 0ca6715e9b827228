"""The typed report: its JSON round trip and the PRNU combination."""

import json
import math

import pytest

from gainfpn_cli.files import FileStamp
from gainfpn_cli.report import Exposure, FrameMotion, Holdout, Layer, Motion, PlaneReport, Prnu, Report
from gainfpn_cli.solve.result import AccurateStats, PaperStats

ACCURATE = PlaneReport("accurate", "G", AccurateStats(6, (12, 30), 5, 1, 0.81), "column",
                       {"pixel": 10.0, "column": 2.5}, {"pixel": 1.0, "column": 0.2, "row": 0.0}, True, 7.9,
                       fpn_base="column")


@pytest.mark.parametrize("exposure", [Exposure("fixed"), Exposure("per-frame", (1.0, 1.03), (1.0, 1.03), (None, 0.001))])
@pytest.mark.parametrize("plane", [ACCURATE, PlaneReport("paper", "Y", PaperStats(12, 1, 0, 64, 0, 4000))])
def test_the_json_of_a_report_reads_back_to_the_same_report(plane, exposure):
    frames = (FrameMotion("b.exr", 300, 280, 0.04, 2.5, [[1.0, 0, 0.5], [0, 1, 0], [0, 0, 1]]),)
    report = Report(motion=Motion("layers", "lowest GRIC", (Layer("shift", 40),), frames, 0, [0.0, 1.5]),
                    prnu_percent=Prnu.combined({"R@00": {"pixel": 1.0, "column": 0.2, "row": 0.0},
                                                "B@11": {"pixel": 1.2, "column": 0.1, "row": 0.05}}),
                    predicted_residual_percent=0.4, holdout=Holdout("c.exr", 0.31, True), estimated_percent=98.5,
                    inputs=(FileStamp("/x/a.exr", 10, 123, "ab" * 32), FileStamp("/x/b.exr", 11, 124, "cd" * 32)),
                    dark=FileStamp("/x/d.exr", 12, 125, "ef" * 32), white_level_dn=4095.0, reference="a.exr",
                    exposure=exposure, planes={"R@00": plane}, config={"solver": {}},
                    timings={"read_s": 0.5}, versions={"numpy": "2"}, warnings=("dark",))
    text = json.dumps(report.to_json())
    assert Report.from_json(json.loads(text)) == report
    assert list(json.loads(text))[:5] == ["version", "status", "prnu_percent", "predicted_residual_percent", "holdout"]
    assert json.loads(text)["planes"]["R@00"]["method"] == plane.method  # flat: the solver's counts beside it
    with pytest.raises(KeyError):
        Report.from_json({k: v for k, v in json.loads(text).items() if k != "inputs"})


def test_prnu_parts_add_in_quadrature_and_planes_combine_as_root_mean_square():
    prnu = Prnu.combined({"a": {"pixel": 3.0, "column": 4.0, "row": 0.0}, "b": {"pixel": 1.0, "column": 0.0, "row": 0.0}})
    assert prnu.planes["a"].total == 5.0 and prnu.planes["b"].total == 1.0
    assert prnu.pixel == pytest.approx(math.sqrt((9 + 1) / 2)) and prnu.column == pytest.approx(math.sqrt(8))
    assert prnu.total == pytest.approx(math.sqrt(5 + 8))
    assert Prnu.combined({}).total is None  # the paper method: no split, nothing measured


def test_times_add_up_to_the_total():
    report = Report(motion=Motion("shift"), timings={"read_s": 1.0, "solve_s": 2.0})
    assert report.with_timings(write_s=0.5).timings == {"read_s": 1.0, "solve_s": 2.0, "write_s": 0.5, "total_s": 3.5}
