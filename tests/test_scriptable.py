"""Results that are what they claim, and a command line a lab pipeline or CI job can script:
apply with the estimate's dark frame, batch's reuse of stored results, evaluate's truth checks,
--json, --strict, -q, defaults in the help, presets, globs, progress only on a terminal."""

from __future__ import annotations

import json
import os
import shutil
import sys

import numpy as np
import pytest
from helpers import SMALL, one_error, run_cli

from gainfpn_cli import checking
from gainfpn_cli.cli import main
from gainfpn_cli.errors import EXIT_REJECTED
from gainfpn_cli.files import read_frame, write_exr
from gainfpn_cli.solve.holdout import Check

# ---------------------------------------------------------------------------
# apply after estimate --dark


def test_apply_gives_the_frames_estimate_wrote_with_its_dark_frame(small_sim, tmp_path):
    dark = tmp_path / "dark.exr"
    write_exr(dark, {"Y": np.full((72, 96), 3.0, np.float32)})
    est = tmp_path / "est"
    run_cli("estimate", small_sim, "-o", est, "-q", "--workers", "1", "--dark", dark)
    applied = tmp_path / "applied"
    run_cli("apply", small_sim, "--gain-map", est / "gain_map.exr", "-o", applied, "-q")  # the dark from the header
    for frame in sorted(small_sim.glob("frame_*.exr")):
        ours = read_frame(applied / frame.name).data
        np.testing.assert_array_equal(ours, read_frame(est / "corrected" / frame.name).data)
    # the dark level is really subtracted (not only equal by accident): without it the frames differ
    k = read_frame(est / "gain_map.exr").data
    np.testing.assert_allclose(ours, (read_frame(frame).data - 3.0) * k, rtol=1e-6)

    other = tmp_path / "other.exr"
    write_exr(other, {"Y": np.full((72, 96), 4.0, np.float32)})
    one_error(run_cli("apply", small_sim, "--gain-map", est / "gain_map.exr", "-o", tmp_path / "x", "--dark", other,
                    ok=False), "is not the dark frame the gain map was estimated with")
    moved = tmp_path / "moved.exr"
    shutil.move(dark, moved)
    one_error(run_cli("apply", small_sim, "--gain-map", est / "gain_map.exr", "-o", tmp_path / "y", ok=False),
               "which is gone; pass it with --dark")
    run_cli("apply", small_sim, "--gain-map", est / "gain_map.exr", "-o", tmp_path / "z", "--dark", moved, "-q")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_a_dark_frame_for_a_map_made_without_one_is_refused(small_sim, small_estimate, tmp_path):
    dark = tmp_path / "dark.exr"
    write_exr(dark, {"Y": np.zeros((72, 96), np.float32)})
    one_error(run_cli("apply", small_sim, "--gain-map", small_estimate / "gain_map.exr", "-o", tmp_path / "o", "--dark", dark,
                    ok=False), "was estimated without a dark frame")


# ---------------------------------------------------------------------------
# batch reuses a result only for the same inputs and config


def test_batch_runs_a_burst_again_when_its_inputs_or_config_changed(tmp_path):
    burst = tmp_path / "b"
    run_cli("simulate", burst, *SMALL)
    manifest = tmp_path / "m.yaml"
    manifest.write_text("bursts:\n  - {name: a, inputs: b}\n")
    out = tmp_path / "out"

    def batch(*extra):
        result = run_cli("batch", manifest, "-o", out, "--json", *extra)
        return json.loads(result.stdout)["bursts"][0]

    assert batch()["earlier"] is False
    assert batch()["earlier"] is True
    os.utime(burst / "frame_002.exr", ns=(1_000_000_000, 1_000_000_000))  # touched: maybe not the same capture
    assert batch()["earlier"] is False
    assert batch()["earlier"] is True
    config = tmp_path / "lam.yaml"
    config.write_text("solver: {lam: 0.01}\n")
    assert batch("-c", config)["earlier"] is False  # another effective config
    assert json.loads((out / "a" / "report.json").read_text())["config"]["solver"]["lam"] == 0.01
    assert batch("-c", config)["earlier"] is True
    assert batch("-c", config, "--overwrite")["earlier"] is False
    from gainfpn_cli.tools.batch import Defaults, load_manifest, run_burst

    # resumed with another solver process count (a cluster's one): the same result, so not run again
    row = run_burst(load_manifest(manifest)[0], out, defaults=Defaults(config=config), solver_workers=1)
    assert row["earlier"] is True
    row = batch("--preset", "paper")
    assert row["earlier"] is False and row["fpn_models"] == "paper"


def test_the_summary_rounds_each_column_the_same_way(tmp_path, small_sim):
    manifest = tmp_path / "m.yaml"
    manifest.write_text(f"bursts:\n  - {{name: a, inputs: {small_sim}}}\n")
    run_cli("batch", manifest, "-o", tmp_path / "out", "-q")
    from gainfpn_cli.tools.batch import COLUMNS

    header, line = (tmp_path / "out" / "summary.csv").read_text().splitlines()
    for column, value in zip(header.split(","), line.split(",")):
        if COLUMNS[column] is not None and value:
            assert len(value.split(".")[-1]) <= COLUMNS[column], (column, value)


# ---------------------------------------------------------------------------
# evaluate refuses another simulation's truth


@pytest.mark.parametrize("options, words", [
    (["--size", "112x72", "--frames", "5"], ["truth is 112x72, the gain map 96x72"]),
    (["--size", "96x72", "--frames", "5", "--cfa", "RGGB"], ["CFA layout RGGB differs from the estimate's (none)"]),
    (["--size", "96x72", "--frames", "5", "--bits", "10"], ["white level 1023 DN", "(255 DN)", "bit depth"]),
    (["--size", "96x72", "--frames", "5", "--seed", "9"], ["differs from the frame frame_000.exr"]),
])
def test_evaluate_refuses_a_truth_that_is_not_the_estimates(small_estimate, tmp_path, options, words):
    other = tmp_path / "other"
    run_cli("simulate", other, *options, "-q")
    one_error(run_cli("evaluate", small_estimate, "--truth", other, "-o", tmp_path / "ev", ok=False), *words)
    assert not (tmp_path / "ev").exists()


# ---------------------------------------------------------------------------
# --json, --strict, -q


def test_json_records_say_what_a_pipeline_needs(small_sim, small_estimate, tmp_path):
    est = json.loads(run_cli("estimate", small_sim, "-o", tmp_path / "e", "--workers", "1", "--json").stdout)
    assert est["status"] == "accepted" and est["holdout"]["passed"] is True
    assert 4.0 < est["prnu_percent"]["total"] < 6.0  # simulated 5 % pixel FPN
    assert set(est["prnu_percent"]) == {"total", "pixel", "column", "row", "planes"}
    assert 0 < est["predicted_residual_percent"] < est["prnu_percent"]["total"]
    assert est["outputs"]["gain_map"] == str((tmp_path / "e" / "gain_map.exr").absolute())
    assert est["warnings"] == []
    applied = json.loads(run_cli("apply", small_sim, "--gain-map", small_estimate / "gain_map.exr", "-o", tmp_path / "a",
                              "--json").stdout)
    assert applied["status"] == "done" and len(applied["outputs"]) == 5
    scores = json.loads(run_cli("evaluate", small_estimate, "--truth", small_sim, "-o", tmp_path / "v", "--json").stdout)
    assert scores["residual_fpn_percent"] < scores["input_fpn_percent"]
    assert scores["evaluation"] == str((tmp_path / "v" / "evaluation.json").absolute())


def test_strict_makes_a_rejected_estimate_exit_with_its_own_status(small_sim, tmp_path, monkeypatch):
    says_no = lambda *args, grids, **kwargs: {g.name: Check(1.5, 0.01, np.ones(1), np.ones(1)) for g in grids}  # noqa: E731
    monkeypatch.setattr(checking, "holdout_checks", says_no)  # the held-out frame says no
    lenient = run_cli("estimate", small_sim, "-o", tmp_path / "a", "--workers", "1", "--json")
    assert json.loads(lenient.stdout)["status"] == "rejected"
    strict = run_cli("estimate", small_sim, "-o", tmp_path / "b", "--workers", "1", "--strict", "-q", ok=False)
    assert strict.exit_code == EXIT_REJECTED == 3
    assert (tmp_path / "b" / "gain_map.exr").is_file()  # k = 1 is still written, as without --strict
    manifest = tmp_path / "m.yaml"
    manifest.write_text(f"bursts:\n  - {{name: a, inputs: {small_sim}}}\n")
    assert run_cli("batch", manifest, "-o", tmp_path / "c", "-q").exit_code == 0
    assert run_cli("batch", manifest, "-o", tmp_path / "c", "-q", "--strict", ok=False).exit_code == EXIT_REJECTED


def test_every_command_has_quiet_and_shows_defaults():
    for name, command in main.commands.items():
        assert "-q" in [opt for p in command.params for opt in p.opts], name
    flat = lambda text: " ".join(text.split())  # noqa: E731 (help is wrapped to the terminal's width)
    assert "Frames in the burst. [default: 8;" in flat(run_cli("simulate", "--help").output)
    assert "[default: 2 (config solver.workers)]" in flat(run_cli("estimate", "--help").output)


def test_quiet_prints_nothing_but_warnings(small_sim, tmp_path):
    made = run_cli("simulate", tmp_path / "s", "--size", "64x64", "--frames", "4", "-q")
    assert made.output == ""
    est = run_cli("estimate", small_sim, "-o", tmp_path / "e", "--workers", "1", "-q")
    assert est.output == ""


def test_the_paper_preset_works(small_sim, tmp_path):
    result = run_cli("estimate", small_sim, "-o", tmp_path / "p", "--preset", "paper", "--workers", "1")
    assert "FPN model paper" in result.output
    assert json.loads((tmp_path / "p" / "report.json").read_text())["config"]["solver"]["method"] == "paper"


# ---------------------------------------------------------------------------
# inputs and progress


def test_a_glob_skips_other_files_as_a_directory_does(small_sim, tmp_path):
    from gainfpn_cli.files import find_frames

    (tmp_path / "b").mkdir()
    for p in small_sim.glob("frame_*.exr"):
        shutil.copy(p, tmp_path / "b" / p.name)
    (tmp_path / "b" / "notes.txt").write_text("n")
    (tmp_path / "b" / "thumb.jpg").write_bytes(b"\xff\xd8")
    from_dir = find_frames([tmp_path / "b"])
    assert find_frames([str(tmp_path / "b" / "*")]) == from_dir and len(from_dir) == 5
    one_error(run_cli("estimate", str(tmp_path / "b" / "*.txt"), "-o", tmp_path / "o", ok=False),
               "pattern matches no EXR or RAW frame (only notes.txt)")


def test_progress_bars_only_on_a_terminal(monkeypatch):
    from gainfpn_cli import cli

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert cli.progress_bars(quiet=False) is None  # a make or CI log gets no carriage-return redraws
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    stage = cli.progress_bars(quiet=False)
    assert callable(stage) and cli.progress_bars(quiet=True) is None
    stage("read", 2)(1)
    cli.close(stage)


def test_messages_never_show_python_none(tmp_path):
    from gainfpn_cli.errors import InputError
    from gainfpn_cli.files import check_consistent

    write_exr(tmp_path / "a.exr", {"Y": np.zeros((30, 30), np.float32)})
    write_exr(tmp_path / "b.exr", {"Y": np.zeros((30, 30), np.float32)}, metadata={"gainfpn:saturation": 200.0})
    with pytest.raises(InputError) as caught:
        check_consistent([read_frame(tmp_path / n).info for n in ("a.exr", "b.exr")])
    assert "white level 200 differs from a.exr (not stated)" in str(caught.value)


def test_the_exit_status_of_a_rejected_estimate_is_documented():
    help_text = run_cli("estimate", "--help").output
    assert f"{EXIT_REJECTED} then with --strict" in " ".join(help_text.split())
