"""Helpers shared by the test modules: small simulated bursts run through the
pipeline in memory, the checks every output must pass, and an EXR writer
independent of gainfpn's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from gainfpn_cli import metrics
from gainfpn_cli.burst import LoadedBurst
from gainfpn_cli.config import load_config
from gainfpn_cli.pipeline import estimate
from gainfpn_cli.sim.simulate import simulate_burst

SHAPE = (64, 80)


def _burst(**options):
    options = {"shape": SHAPE, "n_frames": 6, "seed": 1, **options}
    burst = simulate_burst(**options)
    return burst.frames.astype(np.float32) - burst.sensor.black_level, burst


def _run(frames, saturation=None, **overrides):
    frames = np.asarray(frames, np.float32)[..., None]
    loaded = LoadedBurst([Path(f"f{i}.exr") for i in range(len(frames))], frames, None, ("Y",), saturation, 0)
    cfg = load_config(overrides={"solver.workers": 1, **overrides})
    result = estimate(loaded, cfg)
    _assert_sane(result, cfg)
    return result


def _assert_sane(result, cfg):
    """What every output must be: finite, gauged, physical."""
    k, confidence = result.k[..., 0], result.confidence[..., 0]
    assert np.isfinite(k).all() and np.isfinite(confidence).all()
    assert ((confidence >= 0) & (confidence <= 1)).all()
    est = confidence > 0
    models = {p.fpn_model or "pixel" for p in result.report.planes.values()}
    if models <= {"pixel", "none"}:  # a column / row model also knows the unestimated pixels' gains
        assert (k[~est] == 1).all()
    if est.any():
        low, high = cfg.solver.gain_range
        assert ((k[est] >= low) & (k[est] <= high)).all()
        assert k[est].mean() == pytest.approx(1.0, abs=1e-4)


def _residual(result, burst):
    k, est = result.k[..., 0], result.confidence[..., 0] > 0
    return metrics.residual_fpn_percent(k, burst.gain, est)


def _write_raw_exr(path, pixels, names, fmt="float"):
    """Independent writer (plain OpenImageIO) for fixtures the gainfpn writer would refuse."""
    pixels = np.ascontiguousarray(pixels)
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    spec.channelnames = tuple(names)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels) and out.close()


#: A small simulated burst for command-line tests: 96x72, 5 frames.
SMALL = ["--size", "96x72", "--frames", "5", "-q"]


def run_cli(*args, ok=True):
    """``gainfpn ARGS`` in-process; with ``ok``, assert it succeeded."""
    from click.testing import CliRunner

    from gainfpn_cli.cli import main

    result = CliRunner().invoke(main, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output
    return result


def one_error(result, *words):
    """A user error: exit 1, one line on the output, naming ``words`` and never Python's None."""
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert "None" not in lines[0]
    for word in words:
        assert str(word) in lines[0], lines[0]
