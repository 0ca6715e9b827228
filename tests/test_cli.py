import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from gainfpn_cli import __version__
from gainfpn_cli import files as io
from gainfpn_cli.cli import main


@pytest.fixture()
def runner():
    return CliRunner()


def test_every_command_has_help(runner):
    result = runner.invoke(main, ["--help"])
    assert result.exit_code == 0 and "gain fixed pattern noise" in result.output
    for name, command in main.commands.items():
        sub = runner.invoke(main, [name, "--help"])
        assert sub.exit_code == 0, name
        assert f" {name} [OPTIONS]" in sub.output and command.get_short_help_str()[:20] in sub.output


def test_version(runner):
    result = runner.invoke(main, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output


def test_simulate_default_burst(runner, tmp_path):
    out = tmp_path / "burst"
    result = runner.invoke(main, ["simulate", str(out), "--size", "64x48", "--frames", "3"])
    assert result.exit_code == 0, result.output
    frames = io.read_stack(io.find_frames([out]))
    assert len(frames) == 3 and frames[0].info.shape == (48, 64)
    assert (out / "truth" / "gain.exr").is_file() and (out / "truth" / "homographies.json").is_file()


def test_simulate_dead_leaves_scene(runner, tmp_path):
    out = tmp_path / "leaves"
    result = runner.invoke(main, ["simulate", str(out), "--size", "64x48", "--frames", "2", "--scene", "dead-leaves"])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "truth" / "simulation.json").read_text())["scene"] == "dead-leaves"


def test_simulate_dng_burst_is_readable_raw(runner, tmp_path):
    out = tmp_path / "raw"
    result = runner.invoke(main, ["simulate", str(out), "--preset", "raw12", "--size", "64x48", "--frames", "2"])
    assert result.exit_code == 0, result.output
    frames = io.read_stack(io.find_frames([out]))
    assert [f.info.kind for f in frames] == ["raw", "raw"] and frames[0].info.cfa == "RGGB"


def test_simulate_refuses_to_mix_results(runner, tmp_path):
    out = tmp_path / "b"
    assert runner.invoke(main, ["simulate", str(out), "--size", "32x32", "--frames", "4"]).exit_code == 0
    again = runner.invoke(main, ["simulate", str(out), "--size", "32x32", "--frames", "2"])
    assert again.exit_code == 1
    assert again.output.strip().splitlines() == [
        f"Error: {out}: already holds results of gainfpn (frame_000.exr, frame_001.exr, frame_002.exr, ...); pass "
        "--overwrite to replace them (files gainfpn did not write are left alone)"]
    replaced = runner.invoke(main, ["simulate", str(out), "--size", "32x32", "--frames", "2", "--overwrite"])
    assert replaced.exit_code == 0
    assert sorted(p.name for p in out.glob("frame_*")) == ["frame_000.exr", "frame_001.exr"]


def test_outputs_go_into_new_folders_as_mkdir_p_would(runner, tmp_path):
    # the README's `gainfpn simulate out/burst && gainfpn estimate out/burst -o out/est` on a fresh clone
    sim, est = tmp_path / "out" / "burst", tmp_path / "runs" / "a" / "est"
    assert runner.invoke(main, ["simulate", str(sim), "--size", "96x72", "--frames", "5"]).exit_code == 0
    result = runner.invoke(main, ["estimate", str(sim), "-o", str(est), "--quiet", "--workers", "1"])
    assert result.exit_code == 0, result.output
    assert "exposures differ" not in result.output  # one exposure: nothing divided out, nothing said
    assert (est / "gain_map.exr").is_file()
    assert sorted(p.name for p in (tmp_path / "runs" / "a").iterdir()) == ["est"]  # no staging left beside it
    (tmp_path / "file").write_text("x")
    refused = runner.invoke(main, ["simulate", str(tmp_path / "file" / "burst"), "--size", "32x32", "--frames", "2"])
    assert refused.exit_code == 1
    assert refused.output.strip() == f"Error: {tmp_path / 'file'}: is not a directory, so {tmp_path / 'file' / 'burst'} cannot be made"


def test_simulate_is_deterministic(runner, tmp_path):
    for name in ("a", "b"):
        assert runner.invoke(main, ["simulate", str(tmp_path / name), "--size", "32x32", "--frames", "2",
                                    "--seed", "7"]).exit_code == 0
    a, b = (io.read_frame(tmp_path / n / "frame_001.exr").data for n in ("a", "b"))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--size", "10x10"], "must be at least 22x22"),
        (["--size", "big"], "must be WIDTHxHEIGHT"),
        (["--fpn-pixel", "-0.1"], "--fpn-pixel"),
        (["--format", "tiff"], "--format"),
        (["--bits", "8", "--black", "300"], "black level 300 leaves no range"),
        (["--scene", "leaves"], "neither a built-in scene (procedural, dead-leaves) nor an image file"),
    ],
)
def test_usage_errors_exit_2(runner, tmp_path, args, message):
    result = runner.invoke(main, ["simulate", str(tmp_path / "x"), *args])
    assert result.exit_code == 2 and message in result.output
    assert not (tmp_path / "x").exists()


def test_user_errors_exit_1_with_one_line(runner, tmp_path):
    junk = tmp_path / "scene.png"
    junk.write_bytes(b"not an image at all")
    result = runner.invoke(main, ["simulate", str(tmp_path / "x"), "--scene", str(junk)])
    assert result.exit_code == 1
    assert result.output.startswith("Error: ") and str(junk) in result.output
    assert len(result.output.strip().splitlines()) == 1
    # DNG needs a CFA
    result = runner.invoke(main, ["simulate", str(tmp_path / "y"), "--format", "dng", "--size", "32x32"])
    assert result.exit_code == 1 and "DNG output needs a colour filter array" in result.output
    assert not (tmp_path / "y").exists()  # refused before anything was written


def test_a_burst_exposed_unevenly_is_reported_and_evaluated(runner, tmp_path):
    # gainfpn simulate --exposure-jitter: truth records the drawn exposures, estimate measures them
    # (report.json, summary line) and divides them out; evaluate shows the gain FPN reduced
    sim, est = tmp_path / "sim", tmp_path / "est"
    made = runner.invoke(main, ["simulate", str(sim), "--size", "160x120", "--frames", "6", "--exposure-jitter", "0.05"])
    assert made.exit_code == 0, made.output
    drawn = json.loads((sim / "truth" / "simulation.json").read_text())["exposures"]
    result = runner.invoke(main, ["estimate", str(sim), "-o", str(est), "--workers", "1"])
    assert result.exit_code == 0, result.output
    said = re.search(r"exposures differ by up to ([0-9.]+) % \(divided out\)", result.output)
    assert said and abs(float(said[1]) - 100 * max(abs(c - 1) for c in drawn)) < 0.15
    report = json.loads((est / "report.json").read_text())
    np.testing.assert_allclose(report["exposure"]["relative"], drawn, rtol=2e-3)
    evaluated = runner.invoke(main, ["evaluate", str(est), "--truth", str(sim)])
    assert evaluated.exit_code == 0, evaluated.output
    scores = json.loads((est / "evaluation.json").read_text())
    assert scores["residual_fpn_percent"] < 1.0 < 4.0 < scores["input_fpn_percent"]  # measured 0.77 % from 5 %
