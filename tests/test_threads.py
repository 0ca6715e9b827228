"""Threads in one place: pipeline.estimate called from Python runs BLAS single-threaded, as the
command and its workers do, and gives the command's result bit for bit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
from click.testing import CliRunner

from gainfpn_cli.cli import main
from gainfpn_cli.files import read_exr_planes
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst

CALLER = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from threadpoolctl import threadpool_info
    from gainfpn_cli import pipeline, solving
    from gainfpn_cli.config import load_config

    seen = []
    solve = solving.solve_accurate

    def spy(*args, **kwargs):  # the BLAS threads the solver runs with
        seen.append(max((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"), default=1))
        return solve(*args, **kwargs)

    solving.solve_accurate = spy
    cfg = load_config(overrides={"solver.workers": 1})
    result = pipeline.estimate(pipeline.load_burst([sys.argv[1]], cfg), cfg)
    np.save(sys.argv[2], result.k)
    before = max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")
    print(json.dumps({"in_solve": seen, "outside": before}))
    """
)


def test_a_python_caller_gets_single_threaded_blas_and_the_commands_result(tmp_path):
    save_burst(simulate_burst(shape=(96, 128), n_frames=5, seed=4), tmp_path / "sim", fmt="exr")
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["estimate", str(tmp_path / "sim"), "-o", str(out), "-q", "--workers", "1"])
    assert result.exit_code == 0, result.output
    # a caller that set no thread variables: BLAS starts with one thread per core
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env["OPENBLAS_NUM_THREADS"] = "2"  # as many as a 2-core machine gets by default, on any machine
    done = subprocess.run([sys.executable, "-c", CALLER, str(tmp_path / "sim"), str(tmp_path / "k.npy")],
                          capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    threads = json.loads(done.stdout.strip().splitlines()[-1])
    assert threads["outside"] == 2, "the caller's own BLAS is left as it was"
    assert threads["in_solve"] and set(threads["in_solve"]) == {1}
    planes, _ = read_exr_planes(out / "gain_map.exr")
    np.testing.assert_array_equal(np.load(tmp_path / "k.npy")[..., 0], planes["Y"])


def test_results_come_in_task_order_and_workers_stop_when_they_are_left():
    from multiprocessing import active_children

    from gainfpn_cli.parallel import imap_ordered, map_ordered

    tasks = [-3, 1, -4, 1, -5, 9, -2, 6]
    assert map_ordered(abs, tasks, workers=2) == map_ordered(abs, tasks, workers=1) == [abs(t) for t in tasks]
    taken = imap_ordered(abs, tasks, workers=2)
    assert [next(taken), next(taken)] == [3, 1] and len(active_children()) == 2
    taken.close()  # the caller stops taking results (a failure while folding them in): the pool goes
    assert active_children() == []
