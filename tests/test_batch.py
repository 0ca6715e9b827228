"""gainfpn batch: manifests, a batch here and on a local Dask cluster (a corrupt burst, a killed
worker, a re-run), and the solver's Dask backend."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gainfpn_cli.cli import main
from gainfpn_cli.errors import ConfigError
from gainfpn_cli.files import read_exr_planes
from gainfpn_cli.outdir import MANIFEST, read_manifest
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst
from gainfpn_cli.tools.batch import COLUMNS, INSTALL_HINT, Job, load_manifest, run_batch

OUTPUTS = {"gain_map.exr", "corrected", "report.json", "config.used.yaml", "preview.png", MANIFEST}


@pytest.fixture(scope="module")
def bursts(tmp_path_factory):
    """Three small bursts, a corrupt one (its first frame is text), and a manifest of them."""
    root = tmp_path_factory.mktemp("bursts")
    for seed in (1, 2, 3):
        save_burst(simulate_burst(shape=(96, 128), n_frames=6, seed=seed, scene="dead-leaves"), root / f"b{seed}",
                   fmt="exr")
    (root / "bad").mkdir()
    for i in range(1, 6):
        (root / "bad" / f"frame_{i:03d}.exr").write_bytes((root / "b1" / f"frame_{i:03d}.exr").read_bytes())
    (root / "bad" / "frame_000.exr").write_text("not an image")
    (root / "one.yaml").write_text("solver:\n  workers: 1\n")
    (root / "manifest.yaml").write_text(
        "bursts:\n"
        "  - {name: one, inputs: b1, config: one.yaml}\n"
        "  - {name: broken, inputs: bad}\n"
        "  - {name: two, inputs: 'b2/*.exr'}\n"
        "  - {name: three, inputs: [b3]}\n"
    )
    return root


def _k(folder: Path) -> dict:
    planes, _ = read_exr_planes(folder / "gain_map.exr")
    return planes


def _check_done(out: Path, rows: list, names=("one", "two", "three")):
    by_name = {r["name"]: r for r in rows}
    assert [r["name"] for r in rows] == ["one", "broken", "two", "three"]  # manifest order
    assert by_name["broken"]["status"] == "failed" and "frame_000.exr" in by_name["broken"]["message"]
    for name in names:
        assert by_name[name]["status"] == "done", by_name[name]
        assert set(p.name for p in (out / name).iterdir()) == OUTPUTS
        assert by_name[name]["frames"] == 6 and by_name[name]["motion_model"]
        assert by_name[name]["exposure_spread_percent"] == 0.0  # simulated with one exposure
    assert not (out / "broken").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != MANIFEST]  # no staging left
    assert set(read_manifest(out)) == {"one", "two", "three", "summary.csv", "summary.json"}
    assert json.loads((out / "summary.json").read_text()) == rows
    lines = (out / "summary.csv").read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and len(lines) == 5


def test_a_manifest_is_read_strictly(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("bursts:\n  - {name: a, inputs: [x/*.dng, y], config: c.yaml}\n  - {name: b.2, inputs: z}\n")
    assert load_manifest(path) == [Job("a", (str(tmp_path / "x/*.dng"), str(tmp_path / "y")), tmp_path / "c.yaml"),
                                   Job("b.2", (str(tmp_path / "z"),), None)]
    for text, message in [
        ("frames: []\n", "the one key 'bursts'"),
        ("bursts: []\n", "non-empty list"),
        ("bursts:\n  - {name: a, inputs: x}\n  - {name: a, inputs: y}\n", r"bursts\[1\]\.name: 'a' is used twice"),
        ("bursts:\n  - {name: ../up, inputs: x}\n", r"bursts\[0\]\.name: must be a folder name"),
        ("bursts:\n  - {name: a, inputs: x, preset: fast}\n", r"bursts\[0\]: unknown key\(s\) preset"),
        ("bursts:\n  - {name: a, inputs: []}\n", r"bursts\[0\]\.inputs: must be a path or glob"),
        ("bursts:\n  - {name: a, inputs: x\n", "not valid YAML"),
    ]:
        path.write_text(text)
        with pytest.raises(ConfigError, match=message):
            load_manifest(path)


def test_a_batch_here_reports_a_failing_burst_finishes_the_others_and_resumes(bursts, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["batch", str(bursts / "manifest.yaml"), "-o", str(out)])
    assert result.exit_code == 1, result.output
    assert "3 of 4 bursts done (0 earlier, 0 rejected by the hold-out check), 1 failed" in result.output and "Error: broken:" in result.output
    rows = json.loads((out / "summary.json").read_text())
    _check_done(out, rows)
    # the same as `gainfpn estimate` writes
    alone = tmp_path / "alone"
    assert CliRunner().invoke(main, ["estimate", str(bursts / "b2"), "-o", str(alone), "--quiet"]).exit_code == 0
    assert all(np.array_equal(_k(alone)[c], _k(out / "two")[c]) for c in ("Y", "confidence"))
    # a re-run skips what is done and leaves it untouched
    stamp = (out / "two" / "gain_map.exr").stat().st_mtime_ns
    again = CliRunner().invoke(main, ["batch", str(bursts / "manifest.yaml"), "-o", str(out)])
    assert "3 of 4 bursts done (3 earlier, 0 rejected by the hold-out check), 1 failed" in again.output
    assert (out / "two" / "gain_map.exr").stat().st_mtime_ns == stamp
    rerun = json.loads((out / "summary.json").read_text())
    assert [r["status"] for r in rerun] == ["done", "failed", "done", "done"]
    assert [r["earlier"] for r in rerun] == [True, False, True, True]
    assert [r["prnu_pixel_percent"] for r in rerun] == [r["prnu_pixel_percent"] for r in rows]


def test_without_dask_a_cluster_batch_says_what_to_install(bursts, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    result = CliRunner().invoke(main, ["batch", str(bursts / "manifest.yaml"), "-o", str(tmp_path / "o"),
                                       "--local-cluster", "2"])
    assert result.exit_code == 1 and INSTALL_HINT in result.output
    result = CliRunner().invoke(main, ["batch", str(bursts / "manifest.yaml"), "-o", str(tmp_path / "o"),
                                       "--local-cluster", "2", "--scheduler", "tcp://127.0.0.1:1"])
    assert result.exit_code == 2 and "not both" in result.output


@pytest.fixture(scope="module")
def cluster():
    pytest.importorskip("distributed")
    from gainfpn_cli.tools.batch import local_cluster

    client = local_cluster(2)
    yield client
    client.close()
    client.cluster.close()


@pytest.mark.slow  # a batch of three bursts twice; test_the_solver_runs_its_tiles_on_dask_bit_identically is the small one
def test_a_batch_on_a_local_cluster_survives_a_killed_worker_and_matches_the_local_run(bursts, cluster, tmp_path):
    # the local run as users make it: the command (whose process keeps BLAS single-threaded, as the
    # workers do; this test process has threaded BLAS, whose sums differ in the last bit)
    here = tmp_path / "here"
    command = [str(Path(sys.executable).parent / "gainfpn"), "batch", str(bursts / "manifest.yaml"), "-o", str(here)]
    assert subprocess.run(command, capture_output=True).returncode == 1
    rows_here = json.loads((here / "summary.json").read_text())
    out = tmp_path / "cluster"
    pids = cluster.run(os.getpid)
    killed = []

    def kill_a_busy_worker():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            busy = [address for address, tasks in cluster.processing().items() if tasks]
            if busy:
                time.sleep(0.3)  # well into its burst
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.append(busy[0])
            time.sleep(0.02)

    killer = threading.Thread(target=kill_a_busy_worker)
    killer.start()
    rows, _ = run_batch(load_manifest(bursts / "manifest.yaml"), out, client=cluster)
    killer.join()
    assert killed, "no worker was busy to kill"
    _check_done(out, rows)
    for name in ("one", "two", "three"):  # bit-identical to the run in this process
        assert all(np.array_equal(_k(here / name)[c], _k(out / name)[c]) for c in ("Y", "confidence"))
    assert [r["status"] for r in rows] == [r["status"] for r in rows_here]


def test_the_solver_runs_its_tiles_on_dask_bit_identically(bursts, cluster):
    from gainfpn_cli.config import load_config
    from gainfpn_cli.parallel import DaskExecutor
    from gainfpn_cli.pipeline import estimate, load_burst

    cfg = load_config(overrides={"solver.tile": 32, "solver.method": "accurate"})  # several tiles
    burst = load_burst([bursts / "b1"], cfg)
    local = estimate(burst, cfg)
    remote = estimate(burst, cfg, executor=DaskExecutor(cluster))
    assert local.report.planes["Y"].solver.tiles > 4
    assert np.array_equal(local.k, remote.k) and np.array_equal(local.confidence, remote.confidence)


def test_the_summary_gives_the_largest_exposure_difference_divided_out():
    import dataclasses

    from gainfpn_cli.report import Exposure, Motion, PlaneReport, Prnu, Report
    from gainfpn_cli.solve.result import AccurateStats
    from gainfpn_cli.tools.batch import _row

    plane = PlaneReport("accurate", "Y", AccurateStats(1, (10,), 0, 0, 0.8), "pixel", {}, {"pixel": 5.0})
    report = Report(motion=Motion("affine"), predicted_residual_percent=0.6, planes={"Y": plane},
                    prnu_percent=Prnu.of({"pixel": 5.0, "column": 0.0, "row": 0.0}),
                    exposure=Exposure("per-frame", (1.0, 1.05, 0.97), (1.0, 1.05, 0.97), (None, 0.01, 0.01)))
    assert _row("x", report, 1.0)["exposure_spread_percent"] == 5.0
    report = dataclasses.replace(report, exposure=Exposure("fixed"))  # one exposure: nothing divided out
    assert _row("x", report, 1.0)["exposure_spread_percent"] == 0.0
