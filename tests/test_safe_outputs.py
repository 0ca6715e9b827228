"""--overwrite replaces gainfpn's own outputs only, by name, and never an input (every command)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from helpers import SMALL, one_error, run_cli

from gainfpn_cli import outdir
from gainfpn_cli.errors import InputError


def _tree(folder: Path) -> dict:
    """Every file under ``folder`` with its digest: what a refused command must leave as it was."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_estimate_into_its_own_input_folder_deletes_nothing(tmp_path):
    # the report's case: simulate self && echo notes > self/notes.txt && estimate self -o self --overwrite
    self_ = tmp_path / "self"
    run_cli("simulate", self_, *SMALL)
    (self_ / "notes.txt").write_text("notes\n")
    before = _tree(self_)
    one_error(run_cli("estimate", self_, "-o", self_, "--overwrite", ok=False), "holds the input",
             self_ / "frame_000.exr")
    assert _tree(self_) == before


def test_estimate_into_the_parent_of_its_inputs_deletes_nothing(tmp_path):
    burst = tmp_path / "parent" / "burst"
    run_cli("simulate", burst, *SMALL)
    before = _tree(tmp_path / "parent")
    one_error(run_cli("estimate", burst, "-o", tmp_path / "parent", "--overwrite", ok=False), "holds the input")
    as_out = run_cli("estimate", burst, "-o", burst / "frame_000.exr", "--overwrite", ok=False)
    assert as_out.exit_code == 2 and "is a file" in as_out.output  # click refuses a file as OUT
    assert _tree(tmp_path / "parent") == before


def test_a_dark_frame_inside_out_is_an_input_too(small_sim, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(small_sim / "frame_000.exr", out / "dark.exr")
    one_error(run_cli("estimate", small_sim, "-o", out, "--dark", out / "dark.exr", "--overwrite", ok=False),
             "holds the input", "dark.exr")
    assert (out / "dark.exr").is_file()


def test_apply_never_replaces_the_gain_map_it_applies(small_sim, small_estimate, tmp_path):
    out = tmp_path / "est"
    shutil.copytree(small_estimate, out)
    before = _tree(out)
    one_error(run_cli("apply", small_sim, "--gain-map", out / "gain_map.exr", "-o", out, "--overwrite", ok=False),
             "holds the input", "gain_map.exr")
    assert _tree(out) == before


def test_overwrite_replaces_only_what_gainfpn_wrote_and_says_what_it_left(small_sim, tmp_path):
    out = tmp_path / "est"
    run_cli("estimate", small_sim, "-o", out, "-q", "--workers", "1")
    run_cli("evaluate", out, "--truth", small_sim, "-q")
    (out / "notes.txt").write_text("mine\n")
    (out / "mine").mkdir()
    (out / "mine" / "a.txt").write_text("also mine\n")
    again = run_cli("estimate", small_sim, "-o", out, "-q", "--workers", "1", ok=False)
    one_error(again, "already holds results of gainfpn", "--overwrite")
    replaced = run_cli("estimate", small_sim, "-o", out, "--workers", "1", "--overwrite")
    assert "left untouched" in replaced.output and "notes.txt" in replaced.output and "mine" in replaced.output
    assert (out / "notes.txt").read_text() == "mine\n" and (out / "mine" / "a.txt").read_text() == "also mine\n"
    # the old estimate's evaluation went with it: it would describe a map that is gone
    assert not (out / "evaluation.json").exists() and (out / "gain_map.exr").is_file()


def test_simulate_overwrite_keeps_user_files_and_drops_its_own_stale_frames(tmp_path):
    out = tmp_path / "b"
    run_cli("simulate", out, "--size", "32x32", "--frames", "4", "-q")
    (out / "notes.txt").write_text("notes\n")
    refused = run_cli("simulate", out, "--size", "32x32", "--frames", "2", ok=False)
    one_error(refused, "already holds results of gainfpn", "--overwrite")
    replaced = run_cli("simulate", out, "--size", "32x32", "--frames", "2", "--overwrite")
    assert "left untouched" in replaced.output and "notes.txt" in replaced.output
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "frame_000.exr", "frame_001.exr", "notes.txt", "truth"]  # frames 2 and 3 of the old burst are gone


def test_a_folder_of_user_files_takes_outputs_beside_them(small_sim, tmp_path):
    out = tmp_path / "desk"
    out.mkdir()
    (out / "todo.txt").write_text("x")
    run_cli("simulate", out / "sub", *SMALL)  # a folder the user made, not an input
    made = run_cli("estimate", small_sim, "-o", out, "--workers", "1")
    assert "todo.txt" in made.output and (out / "gain_map.exr").is_file() and (out / "todo.txt").read_text() == "x"


def test_evaluate_writes_where_asked_and_overwrites_only_its_file(small_sim, small_estimate, tmp_path):
    est = tmp_path / "est"
    shutil.copytree(small_estimate, est)
    elsewhere = tmp_path / "ev"
    run_cli("evaluate", est, "--truth", small_sim, "-o", elsewhere, "-q")
    assert (elsewhere / "evaluation.json").is_file() and not (est / "evaluation.json").exists()
    one_error(run_cli("evaluate", est, "--truth", small_sim, "-o", elsewhere, ok=False), "evaluation.json", "--overwrite")
    run_cli("evaluate", est, "--truth", small_sim, "-o", elsewhere, "--overwrite", "-q")
    run_cli("evaluate", est, "--truth", small_sim, "-q")
    before = {k: v for k, v in _tree(est).items() if k != "evaluation.json"}
    run_cli("evaluate", est, "--truth", small_sim, "--overwrite", "-q")
    assert {k: v for k, v in _tree(est).items() if k != "evaluation.json"} == before


def test_batch_refuses_an_out_that_holds_a_burst_and_a_folder_it_did_not_write(small_sim, tmp_path):
    manifest = tmp_path / "bursts.yaml"
    manifest.write_text(f"bursts:\n  - name: a\n    inputs: {small_sim}\n")
    one_error(run_cli("batch", manifest, "-o", small_sim.parent, "-q", ok=False), "holds the input")
    out = tmp_path / "out"
    (out / "a").mkdir(parents=True)
    (out / "a" / "keep.txt").write_text("k")
    one_error(run_cli("batch", manifest, "-o", out, "-q", ok=False), "was not written by gainfpn batch", "--overwrite")
    assert (out / "a" / "keep.txt").read_text() == "k"


def test_bench_overwrite_keeps_other_files(tmp_path, monkeypatch):
    from gainfpn_cli.tools import bench

    def fake_run(folder, **kwargs):  # the bench's points are measured elsewhere; here only its outputs matter
        (Path(folder) / "results.md").write_text("| point |\n")
        (Path(folder) / "results.json").write_text("{}")

    monkeypatch.setattr(bench, "run", fake_run)
    out = tmp_path / "b"
    run_cli("bench", "--quick", "-o", out, "-q")
    (out / "mine.md").write_text("m")
    one_error(run_cli("bench", "--quick", "-o", out, "-q", ok=False), "--overwrite")
    result = run_cli("bench", "--quick", "-o", out, "--overwrite")
    assert "mine.md" in result.output and (out / "mine.md").read_text() == "m"


# ---------------------------------------------------------------------------
# the mechanism


def test_a_failed_commit_puts_the_folder_back(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    outdir.record(out, ["a.txt"], "apply")
    plan = outdir.prepare(out, command="apply", names=["a.txt", "b.txt"], overwrite=True)
    real_replace = outdir.os.replace
    calls = []

    def failing(src, dst):
        calls.append(dst)
        if Path(dst).name == "b.txt" and Path(dst).parent == out:
            raise OSError("disk full")
        return real_replace(src, dst)

    with pytest.raises(InputError, match="disk full"):  # one line for the user, not a traceback
        with outdir.staged(plan) as tmp:
            (tmp / "a.txt").write_text("new a")
            (tmp / "b.txt").write_text("new b")
            monkeypatch.setattr(outdir.os, "replace", failing)
    monkeypatch.undo()
    assert (out / "a.txt").read_text() == "old a" and not (out / "b.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging or old folder left


def test_a_manifest_cannot_name_files_outside_its_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "precious").write_text("p")
    (out / outdir.MANIFEST).write_text(json.dumps({"entries": {"../precious": "apply", "x/y": "apply",
                                                               "ok.exr": "apply"}}))
    assert outdir.read_manifest(out) == {"ok.exr": "apply"}
    (out / "ok.exr").write_text("o")
    plan = outdir.prepare(out, command="apply", names=[], overwrite=True)
    with outdir.staged(plan):
        pass
    assert (tmp_path / "precious").read_text() == "p" and not (out / "ok.exr").exists()


def test_an_input_inside_a_replaced_folder_is_refused(tmp_path):
    out = tmp_path / "out"
    (out / "corrected").mkdir(parents=True)
    frame = out / "corrected" / "f.exr"
    frame.write_text("f")
    outdir.record(out, ["corrected"], "estimate")
    with pytest.raises(InputError, match="would be replaced but holds the input"):
        outdir.prepare(out, command="estimate", names=["corrected"], inputs=[frame], overwrite=True,
                       beside_inputs=True)


def test_a_folder_of_an_outputs_name_that_gainfpn_did_not_write_is_never_replaced(small_sim, tmp_path):
    out = tmp_path / "out"
    (out / "corrected").mkdir(parents=True)
    (out / "corrected" / "notes.txt").write_text("mine\n")
    for extra in ([], ["--overwrite"]):
        one_error(run_cli("estimate", small_sim, "-o", out, "--workers", "1", *extra, ok=False),
                  out / "corrected", "was not written by gainfpn")
    assert (out / "corrected" / "notes.txt").read_text() == "mine\n"
    config = tmp_path / "no_frames.yaml"
    config.write_text("output: {corrected: false}\n")  # a run that writes no corrected/ leaves it alone
    run_cli("estimate", small_sim, "-o", out, "--workers", "1", "-c", config, "-q")
    assert (out / "corrected" / "notes.txt").read_text() == "mine\n" and (out / "gain_map.exr").is_file()


def test_the_config_a_run_reads_is_an_input_too(small_sim, tmp_path):
    out = tmp_path / "out"
    run_cli("estimate", small_sim, "-o", out, "--workers", "1", "-q")
    edited = out / "config.used.yaml"
    edited.write_text(edited.read_text().replace("lam: 0.0", "lam: 0.001"))
    before = edited.read_text()
    one_error(run_cli("estimate", small_sim, "-o", out, "-c", edited, "--overwrite", ok=False), "holds the input",
              "config.used.yaml")
    assert edited.read_text() == before
