import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gainfpn_cli import files as io
from gainfpn_cli import metrics
from gainfpn_cli.cli import main
from gainfpn_cli.config import Config, load_config
from gainfpn_cli.outdir import MANIFEST
from gainfpn_cli.outputs import write_estimate
from gainfpn_cli.pipeline import estimate, load_burst
from gainfpn_cli.report import PlaneReport
from gainfpn_cli.sim.motion import Shake
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst
from gainfpn_cli.solve.result import PaperStats


@pytest.fixture(scope="module")
def exr_burst(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim")
    burst = simulate_burst(shape=(96, 128), n_frames=6, seed=21)
    save_burst(burst, folder, fmt="exr")
    return folder, burst


def _run(runner, *args):
    return runner.invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_simulate_estimate_evaluate_improves_the_burst(exr_burst, tmp_path):
    # the CI smoke test of issue 5: a tiny burst through the whole tool
    folder, _ = exr_burst
    runner = CliRunner()
    out = tmp_path / "out"
    result = _run(runner, "estimate", folder, "-o", out, "--quiet", "--workers", "1")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "config.used.yaml", "corrected", "gain_map.exr",
                                                      "preview.png", "report.json"]
    assert len(list((out / "corrected").glob("*.exr"))) == 6
    scores_run = _run(runner, "evaluate", out, "--truth", folder)
    assert scores_run.exit_code == 0 and "MSE reduction" in scores_run.output
    scores = json.loads((out / "evaluation.json").read_text())
    # 96x128, 6 frames (one held out): measured ~15x; the issue asks 12x for 8 frames
    assert scores["mse_before"] / scores["mse_after"] > 8
    assert scores["residual_fpn_percent"] < 1.2


def test_outputs_are_complete_and_documented(exr_burst, tmp_path):
    folder, burst = exr_burst
    cfg = load_config(overrides={"solver.workers": 1})
    loaded = load_burst([folder], cfg)
    result = estimate(loaded, cfg)
    write_estimate(result, loaded, cfg, tmp_path / "o")
    planes, attrs = io.read_exr_planes(tmp_path / "o" / "gain_map.exr")
    assert set(planes) == {"Y", "confidence", "defect"}
    k, conf = planes["Y"], planes["confidence"]
    assert k.dtype == np.float32 and k.shape == burst.gain.shape
    assert np.all((conf >= 0) & (conf <= 1)) and np.all(k[conf == 0] == 1.0)
    assert k[conf > 0].mean() == pytest.approx(1.0, abs=1e-5)
    assert attrs["gainfpn:motion_model"] in ("translation", "affine", "homography")
    assert load_config(tmp_path / "o" / "config.used.yaml") == cfg
    assert json.loads(attrs["gainfpn:inputs"]) == [str(p.absolute()) for p in loaded.paths]
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    for key in ("motion", "planes", "holdout", "timings", "versions", "predicted_residual_percent", "prnu_percent",
                "config", "status"):
        assert key in report
    assert [Path(i["path"]) for i in report["inputs"]] == [p.absolute() for p in loaded.paths]
    assert all(len(i["sha256"]) == 64 and i["size_bytes"] > 0 for i in report["inputs"])
    assert set(report["timings"]) == {"read_s", "motion_s", "defects_s", "solve_s", "holdout_s", "write_s", "total_s"}
    assert report["timings"]["total_s"] == pytest.approx(sum(v for k_, v in report["timings"].items()
                                                             if k_ != "total_s"))
    # one unit convention: no fractions beside the percentages
    assert not [k_ for k_ in report if "fraction" in k_]
    assert report["holdout"]["passed"] is True
    corrected = io.read_frame(tmp_path / "o" / "corrected" / "frame_000.exr").data[..., 0]
    np.testing.assert_allclose(corrected, burst.frames[0] * k, rtol=1e-6)


def test_holdout_rejects_an_estimate_that_does_not_help(exr_burst, monkeypatch):
    # a solver that returns a harmful map (10 % random gains) must be caught on
    # the held-out frame: k = 1 is written, with a warning and the ratio
    import gainfpn_cli.solving as solving

    folder, _ = exr_burst
    cfg = load_config(overrides={"solver.workers": 1})
    burst = load_burst([folder], cfg)

    def harmful(burst_, frames, excluded, exposures, used, H, cfg_, progress, **kwargs):  # the check's fit too
        k = 1 + 0.1 * np.random.default_rng(0).standard_normal(frames.shape[1:])
        report = {"Y": PlaneReport("harmful", "Y", PaperStats(1, 0, 0, 0, 0, 0))}
        return solving.Planes(k, np.ones(frames.shape[1:]), report, {}, np.zeros(frames.shape[1:], bool))

    monkeypatch.setattr(solving, "solve_planes", harmful)
    result = estimate(burst, cfg)
    assert result.report.holdout.passed is False and result.report.holdout.residual_ratio > 1
    assert np.all(result.k == 1.0) and np.all(result.confidence == 0.0)
    assert "k = 1 (no correction) was written" in result.warnings[0]


def test_holdout_accepts_a_good_estimate(exr_burst):
    folder, _ = exr_burst
    cfg = load_config(overrides={"solver.workers": 1})
    result = estimate(load_burst([folder], cfg), cfg)
    # 5 % FPN against ~1 % temporal noise: k must cut the held-out residual well below 1
    assert result.report.holdout.passed and result.report.holdout.residual_ratio < 0.5


def test_existing_output_is_not_mixed(exr_burst, tmp_path):
    folder, _ = exr_burst
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    runner = CliRunner()
    result = _run(runner, "estimate", folder, "-o", out, "--quiet", "--workers", "1")
    assert result.exit_code == 0
    result = _run(runner, "estimate", folder, "-o", out, "--quiet", "--workers", "1")
    assert result.exit_code == 1 and "already holds results of gainfpn" in result.output
    result = _run(runner, "estimate", folder, "-o", out, "--quiet", "--overwrite", "--workers", "1")
    assert result.exit_code == 0
    assert (out / "mine.txt").read_text() == "keep me" and (out / "gain_map.exr").exists()
    assert not list(tmp_path.glob(".out.*"))  # no staging left behind


def test_failure_leaves_no_partial_output(tmp_path):
    frames = tmp_path / "static"
    burst = simulate_burst(shape=(64, 80), n_frames=4, seed=1, shake=Shake(translation_px=0.0, rotation_deg=0.0))
    save_burst(burst, frames, fmt="exr")
    result = CliRunner().invoke(main, ["estimate", str(frames), "-o", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 1
    assert result.output.startswith("Error: ") and "no motion" in result.output
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))


def test_apply_corrects_other_captures_and_checks_size(exr_burst, tmp_path):
    folder, burst = exr_burst
    runner = CliRunner()
    _run(runner, "estimate", folder, "-o", tmp_path / "est", "--quiet", "--workers", "1")
    gain = tmp_path / "est" / "gain_map.exr"
    result = _run(runner, "apply", "--gain-map", gain, folder / "frame_002.exr", "-o", tmp_path / "applied", "-q")
    assert result.exit_code == 0, result.output
    k = io.read_exr_planes(gain)[0]["Y"]
    out = io.read_frame(tmp_path / "applied" / "frame_002.exr").data[..., 0]
    np.testing.assert_allclose(out, burst.frames[2] * k, rtol=1e-6)
    io.write_exr(tmp_path / "small.exr", {"Y": np.ones((10, 12))})
    result = runner.invoke(main, ["apply", "--gain-map", str(gain), str(tmp_path / "small.exr"), "-o",
                                  str(tmp_path / "bad"), "-q"])
    assert result.exit_code == 1 and "small.exr: frame is 12x10" in result.output
    assert not (tmp_path / "bad").exists()


def test_paper_method_end_to_end(exr_burst, tmp_path):
    folder, _ = exr_burst
    result = _run(CliRunner(), "estimate", folder, "-o", tmp_path / "p", "--method", "paper", "--workers", "1")
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "p" / "report.json").read_text())
    assert report["planes"]["Y"]["method"] == "paper"
    # the paper method's confidence is a status (1, 0.5, 0), not a standard error
    assert report["predicted_residual_percent"] is None
    assert "predicted residual" not in result.output and "PRNU not measured" in result.output


def test_config_errors_exit_1(exr_burst, tmp_path):
    folder, _ = exr_burst
    bad = tmp_path / "bad.yaml"
    bad.write_text("solver: {blok_size: 3}\n")
    result = CliRunner().invoke(main, ["estimate", str(folder), "-o", str(tmp_path / "o"), "-c", str(bad)])
    assert result.exit_code == 1
    assert "solver.blok_size: unknown key (did you mean 'block_size'?)" in result.output


def test_reference_out_of_range(exr_burst, tmp_path):
    folder, _ = exr_burst
    result = CliRunner().invoke(main, ["estimate", str(folder), "-o", str(tmp_path / "o"), "--reference", "9"])
    assert result.exit_code == 1 and "input.reference is 9 but there are only 6 frames" in result.output


def test_presets_load():
    for name in ("fast", "balanced", "accurate", "paper"):
        assert load_config(preset=name) != Config() or name == "balanced"


@pytest.mark.parametrize("seed", [2, 3])
def test_a_moving_object_is_left_out_of_the_solve(tmp_path, seed):
    # issue 4: an object covering 10 % of the frame moves on its own; under a
    # single global warp (auto now follows it with a layer of its own, see the
    # next test) its pixels must be masked. Measured MSE reduction off the
    # object (120x160, 6 frames, seeds 2 / 3): 18.5 / 22.3x without an object;
    # with it unmasked 4.8 / 5.5x, masked 15.3 / 10.7x (before the pixel model
    # shrank uncertain k: 3.6 / 2.8x and 14.6 / 8.4x, asserted as masked >= 6x
    # and >= 2x unmasked).
    burst = simulate_burst(shape=(120, 160), n_frames=6, seed=seed, moving_object=0.1)
    save_burst(burst, tmp_path, fmt="exr")
    frame0 = burst.frames[0].astype(np.float32)
    ratios = {}
    for mask in (False, True):
        cfg = load_config(overrides={"solver.workers": 1, "motion.mask_moving": mask, "motion.model": "affine"})
        result = estimate(load_burst([tmp_path], cfg), cfg)
        k = result.k[..., 0]
        off = (result.confidence[..., 0] > 0) & ~burst.moving[0] & metrics.interior_mask(k.shape, 8)
        ratios[mask] = metrics.mse(frame0, burst.ideal[0], off) / metrics.mse(k * frame0, burst.ideal[0], off)
        moving = result.report.motion.moving_percent
        assert (moving is None) if not mask else (len(moving) == 6 and all(8 < m < 30 for m in moving))
    assert ratios[True] >= 1.6 * ratios[False] and ratios[True] >= 9, ratios


def test_a_nearer_plane_is_corrected_through_its_own_layer(tmp_path):
    # issue 4: parallax. A disk over 10 % of the frame is a nearer plane (displaced twice as far as the
    # background). Measured, 160x200x6 dead leaves, seeds 2 / 3 / 4 (5 held out), MSE reduction over
    # the frame (on the disk): layers 4.7x (2.9x) / 6.0x (4.7x) / 7.6x (4.3x); one homography, its
    # pixels masked where found, 1.4x (0.4x) / 2.8x (0.7x) / 4.1x (1.0x): the disk worse than none.
    # The accurate solver's figures: on this aliased 5-frame fit auto tries both solvers and the
    # hold-out keeps the scene solver (over the frame 10.1x against 9.0x; seeds 2 / 3: 6.2x against
    # 5.0x, 8.0x against 6.2x), which estimates less of the disk's rim (docs/limits.md)
    burst = simulate_burst(shape=(160, 200), n_frames=6, seed=5, moving_object=0.1, parallax=1.0,
                           scene="dead-leaves")
    save_burst(burst, tmp_path, fmt="exr")
    frame0 = burst.frames[0].astype(np.float32)
    interior = metrics.interior_mask(frame0.shape, 8)
    disk = burst.moving[0] & interior
    ratios, on_disk = {}, {}
    for model in ("auto", "homography"):
        cfg = load_config(overrides={"solver.workers": 1, "motion.model": model, "solver.method": "accurate"})
        result = estimate(load_burst([tmp_path], cfg), cfg)
        k = result.k[..., 0]
        ratios[model] = metrics.mse(frame0, burst.ideal[0], interior) / metrics.mse(k * frame0, burst.ideal[0], interior)
        on_disk[model] = metrics.mse(frame0, burst.ideal[0], disk) / metrics.mse(k * frame0, burst.ideal[0], disk)
        if model == "auto":
            assert result.report.motion.model == "layers"
            assert [(x.model, x.points) for x in result.report.motion.layers] == [("shift", pytest.approx(40, abs=30))]
            assert (result.confidence[..., 0][disk] > 0).mean() >= 0.8
    assert ratios["auto"] >= 1.5 * ratios["homography"] and on_disk["auto"] >= 2.0, (ratios, on_disk)


@pytest.mark.parametrize("kind, model", [("wobble", "rolling"), ("distortion", "mesh")])
def test_a_burst_no_single_warp_explains_is_corrected_through_its_field(kind, model, tmp_path):
    # dead leaves, 200x260x6, 0.7 px waves, seed 11 (12): with the field model
    # 5.6x (7.7x) for the wobble and 6.9x (4.5x) for the distortion; with the
    # best homography forced 0.19x (1.19x) and 0.8x (0.26x) -- worse than none
    burst = simulate_burst(shape=(200, 260), n_frames=6, seed=11, shake=Shake(**{f"{kind}_px": 0.7}),
                           scene="dead-leaves")
    save_burst(burst, tmp_path, fmt="exr")
    cfg = load_config(overrides={"solver.workers": 1})
    result = estimate(load_burst([tmp_path], cfg), cfg)
    assert result.report.motion.model == model
    frame0 = burst.frames[0].astype(np.float64) - burst.sensor.black_level
    k = result.k[..., 0]
    assert metrics.mse(frame0, burst.ideal[0]) > 4 * metrics.mse(k * frame0, burst.ideal[0])


def test_colour_channels_and_a_later_reference_share_the_masks_and_the_solve():
    # the moving-pixel masks reach every channel (they are broadcast, not
    # copied); a reference that is not the first frame is solved on a
    # reference-first copy. Measured (120x160, seed 3, 10 % object masked
    # under one affine warp, 12-18 % of each frame): every channel's k equals
    # the grey burst's (channel gains 0.5 / 1 / 2); reference 2: 0.88 %
    # residual, as reference 0
    from pathlib import Path

    from gainfpn_cli.burst import LoadedBurst

    burst = simulate_burst(shape=(120, 160), n_frames=6, seed=3, moving_object=0.1)
    grey = burst.frames.astype(np.float32) - burst.sensor.black_level
    paths = [Path(f"f{i}.exr") for i in range(6)]

    def run(frames, channels, reference=0):
        loaded = LoadedBurst(paths, frames, None, channels, None, reference)
        return estimate(loaded, load_config(overrides={"solver.workers": 1, "input.reference": reference,
                                                       "motion.model": "affine"}))  # the object is masked

    mono = run(grey[..., None].copy(), ("Y",))
    assert min(mono.report.motion.moving_percent) > 5  # the object's masks, to share
    rgb = run(grey[..., None] * np.array([0.5, 1.0, 2.0], np.float32), ("R", "G", "B"))
    for c in range(3):
        np.testing.assert_allclose(rgb.k[..., c], mono.k[..., 0], atol=1e-5)
    later = run(grey[..., None].copy(), ("Y",), reference=2)
    assert later.report.reference == "f2.exr"
    est = later.confidence[..., 0] > 0
    assert metrics.residual_fpn_percent(later.k[..., 0], burst.gain, est) < 1.2


def test_a_forced_motion_model_the_frames_do_not_follow_is_refused(tmp_path):
    # the hold-out frame is aligned by the same wrong model, so it cannot catch the misaligned map
    # (docs/bench/holdout_check.py: forced translations on rotating bursts were accepted, 0.79x)
    frames = tmp_path / "rotating"
    save_burst(simulate_burst(shape=(96, 128), n_frames=6, seed=3, shake=Shake(rotation_deg=1.0)), frames, fmt="exr")
    config = tmp_path / "translation.yaml"
    config.write_text("motion:\n  model: translation\n")
    result = CliRunner().invoke(main, ["estimate", str(frames), "-o", str(tmp_path / "out"), "-c", str(config), "-q"])
    assert result.exit_code == 1
    assert result.output.startswith("Error: motion.model translation leaves out how the frames move: "), result.output
    assert "use motion.model auto or homography" in result.output
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))
