"""Properties every estimate has (issue 7): over random small bursts the
outputs are finite, gauged and physical or the burst is refused by name; the
same inputs give bit-identical outputs for any worker count and run, and the
order of the non-reference frames does not matter."""

from __future__ import annotations

import json

import numpy as np
import OpenImageIO as oiio
import pytest
from click.testing import CliRunner
from helpers import _burst, _run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gainfpn_cli.cli import main
from gainfpn_cli.errors import EstimationError
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n_frames=st.integers(3, 6),
    fpn=st.floats(0.0, 0.08),
    exposure=st.floats(0.05, 1.5),
    shake_px=st.floats(0.0, 4.0),
    scene=st.sampled_from(["procedural", "dead-leaves"]),
    method=st.sampled_from(["accurate", "paper"]),
)
def test_random_bursts_give_sane_maps_or_a_named_refusal(seed, n_frames, fpn, exposure, shake_px, scene, method):
    sensor = with_overrides(PRESETS["paper"], fpn_pixel=fpn)
    burst = simulate_burst(shape=(64, 80), n_frames=n_frames, seed=seed, sensor=sensor, exposure=exposure,
                           shake=Shake(translation_px=shake_px), scene=scene)
    frames = burst.frames.astype(np.float32) - burst.sensor.black_level
    try:
        _run(frames, burst.saturation, **{"solver.method": method})  # asserts the outputs are sane
    except EstimationError as exc:
        message = str(exc)
        assert message and "\n" not in message and "Traceback" not in message


def test_frame_order_does_not_matter_except_the_reference():
    frames, burst = _burst()
    options = {"output.holdout": False}  # the hold-out takes the last frame: order would choose it
    base = _run(frames, burst.saturation, **options)
    shuffled = _run(frames[[0, 3, 1, 5, 2, 4]], burst.saturation, **options)
    np.testing.assert_array_equal(shuffled.k, base.k)
    np.testing.assert_array_equal(shuffled.confidence, base.confidence)


@pytest.mark.parametrize("method", ["accurate", "paper"])
def test_outputs_are_bit_identical_across_runs_and_worker_counts(tmp_path, method):
    burst = simulate_burst(shape=(64, 80), n_frames=5, seed=3)
    save_burst(burst, tmp_path / "sim", fmt="exr")
    runs = []
    for i, workers in enumerate((1, 2, 2)):
        out = tmp_path / f"out{i}"
        result = CliRunner().invoke(main, ["estimate", str(tmp_path / "sim"), "-o", str(out), "--quiet",
                                           "--workers", str(workers), "--method", method])
        assert result.exit_code == 0, result.output
        runs.append(out)
    first = _outputs(runs[0])
    for out in runs[1:]:
        assert _outputs(out) == first


def _outputs(out):
    """Everything a run writes, less what must differ (timings; the config's worker count, in the
    report and config.used.yaml)."""
    files = {}
    for path in sorted(out.rglob("*.exr")):
        image = oiio.ImageInput.open(str(path))
        pixels = image.read_image("float").tobytes()
        image.close()
        files[str(path.relative_to(out))] = pixels
    report = json.loads((out / "report.json").read_text())
    report.pop("timings")
    report.pop("config")  # the worker count
    files["report"] = json.dumps(report, sort_keys=True)
    files["preview"] = (out / "preview.png").read_bytes()
    return files
