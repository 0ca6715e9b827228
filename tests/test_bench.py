import json

import pytest
from click.testing import CliRunner

from gainfpn_cli.cli import main
from gainfpn_cli.tools import bench
from gainfpn_cli.tools.bench import BurstSpec, Point


def test_a_small_plan_runs_every_kind_of_point(tmp_path, monkeypatch):
    base = BurstSpec(shape=(64, 80), n_frames=6)
    points = [Point("reference", "floor", base, kind="floor"),
              Point("reference", "flat field", base, kind="flat-field"),
              Point("preset", "fast", base, preset="fast"),
              Point("flow_error", "0.8 px", base, kind="flow-error", flow_error_px=0.8),
              Point("motion_model", "translation", BurstSpec(shape=(64, 80), n_frames=6, motion="4 px shake"),
                    overrides={"motion.model": "translation"}),  # refused: the frames turn
              Point("motion_accuracy", "motion", BurstSpec(shape=(120, 160), n_frames=4, scene="procedural",
                                                           motion="25 px drift"), kind="motion", seeds=2),
              Point("confidence", "dark", BurstSpec(shape=(64, 80), n_frames=6, exposure=0.15))]
    monkeypatch.setattr(bench.measure, "plan", lambda quick, groups=(): points)  # the plan run() follows
    rows = {r["label"]: r for r in bench.run(tmp_path, quick=True)}
    floor, flat, fast, flow, motion = (rows[k] for k in ("floor", "flat field", "fast", "0.8 px", "motion"))
    assert floor["residual_fpn_percent"] == pytest.approx(0.0, abs=1e-3)  # the true gains
    # 6 flat frames of ~95 DN: each pixel mean has ~0.5 % temporal noise
    assert flat["residual_fpn_percent"] < 1.0 < flat["input_fpn_percent"]
    assert floor["mse_after"] <= fast["mse_after"] < fast["mse_before"]
    assert set(fast["timings"]) >= {"read_s", "motion_s", "solve_s", "write_s", "total_s"}
    assert flow["flow_error_px"] == 0.8 and flow["mse_ratio"] > 0
    assert fast["frame_mse_ratio"] == pytest.approx(fast["frame_mse_before"] / fast["frame_mse_after"])
    assert len(motion["motion_worst_px"]) == 2 and max(motion["motion_worst_px"]) < 0.5  # sub-pixel on 2 seeds
    assert len(motion["refined_worst_px"]) == 2 and max(motion["refined_worst_px"]) < 0.5
    assert rows["translation"]["refused"].startswith("motion.model translation leaves out how the frames move")
    assert all(r["peak_rss_mb"] > 10 for r in rows.values())
    summary = json.loads((tmp_path / "results.json").read_text())
    assert summary["machine"]["cpus"] >= 1 and len(summary["points"]) == 7
    dark = rows["dark"]  # 64x80: too small for the two halves, so the solver's own sigma_k
    assert len(dark["confidence_deciles"]) == 10 and dark["confidence_calibrated"] is False
    table = (tmp_path / "results.md").read_text()
    assert "| motion_model | translation | 80x64x6 | refused |" in table
    assert all(f"| {label} |" in table for label in rows)
    assert "| dark | 80x64x6 |" in table.split("Confidence:")[1]  # its own table
    assert not (tmp_path / "scratch").exists()  # the bursts are cleaned up


def test_background_rms_is_the_trajectory_error_off_the_moving_object():
    import numpy as np

    from gainfpn_cli.sim.simulate import simulate_burst

    burst = simulate_burst(shape=(60, 80), n_frames=2, seed=3, moving_object=0.1)
    H = burst.homographies[1]
    assert bench.background_rms(H, burst, 1) == 0.0
    shifted = np.array([[1.0, 0.0, 0.3], [0.0, 1.0, 0.4], [0.0, 0.0, 1.0]]) @ H  # 0.5 px off everywhere
    assert bench.background_rms(shifted, burst, 1) == pytest.approx(0.5)


@pytest.mark.slow
def test_quick_bench_from_the_command_line(tmp_path):
    out = tmp_path / "bench"
    result = CliRunner().invoke(main, ["bench", "--quick", "--quiet", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "paper as published" in (out / "results.md").read_text() and result.output == ""  # --quiet: nothing


def test_groups_select_points_and_unknown_groups_are_named():
    every = bench.plan(False)
    chosen = bench.plan(False, ("motion_model", "refine"))
    assert chosen and {p.group for p in chosen} == {"motion_model", "refine"}
    assert chosen == [p for p in every if p.group in ("motion_model", "refine")]
    # motion no single warp explains: the automatic choice against a forced homography, on the same bursts
    waves = {p.label: p.burst for p in chosen if p.burst.wobble_px or p.burst.distortion_px}
    assert waves["wobble 1 px, auto"] == waves["wobble 1 px, homography"] != waves["distortion 1 px, auto"]
    near = {p.label: p.burst for p in chosen if p.burst.parallax}
    assert near["parallax 1.0, auto"] == near["parallax 1.0, homography"] and len(near) == 2
    assert len({p.burst.key for p in chosen}) == 4  # the keys tell the bursts apart (plain, wobble, distortion, near)
    with pytest.raises(ValueError, match="unknown bench group.*nope.*motion_model"):
        bench.plan(True, ("nope",))
    result = CliRunner().invoke(main, ["bench", "--quick", "--group", "nope", "-o", "unused"])
    assert result.exit_code == 2 and "unknown bench group" in result.output


def test_the_scene_model_group_compares_both_solvers_on_the_same_bursts():
    points = bench.plan(False, ("scene_model",))
    by_burst = {}
    for p in points:
        by_burst.setdefault(p.burst.key, set()).add(p.overrides["solver.method"])
    assert all(methods == {"accurate", "scene"} for methods in by_burst.values())
    keys = set(by_burst)
    assert len(keys) == 11  # 8 / 16 / 32 frames, raw12 x 2 scenes x 2 counts, noise-free x blur x 2 counts
    assert sum("-clean" in k for k in keys) == 4 and sum("-b1" in k for k in keys) == 2
    assert sum(k.endswith("-raw12") for k in keys) == 4


def test_the_table_gives_the_whole_frame_ratio_where_planes_were_turned_away():
    from gainfpn_cli.tools.bench.report import markdown

    row = {"group": "scaling_frames", "label": "RGGB", "kind": "pipeline", "burst": {"shape": [64, 80], "n_frames": 6},
           "residual_fpn_percent": 0.5, "mse_before": 2.0, "mse_after": 1.2, "mse_ratio": 1.66,
           "frame_mse_ratio": 1.26, "peak_rss_mb": 100.0, "timings": {}}
    machine = {"cpus": 2, "processor": "x", "platform": "y", "python": "3"}
    summary = {"machine": machine, "quick": True, "duration_s": 1.0}
    half = markdown({**summary, "points": [{**row, "estimated_percent": 50.0}]})
    assert "| 1.7 (frame 1.3) |" in half
    whole = markdown({**summary, "points": [{**row, "estimated_percent": 99.9}]})
    assert "| 1.7 |" in whole and "frame" not in whole.split("| RGGB |")[1]
