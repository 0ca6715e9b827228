"""Ctrl-C and SIGTERM during the solve or the write (issue 7): the command
stops at once, its worker processes with it, and leaves neither a result
under its final name nor a staging directory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst

pytestmark = pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds worker processes through /proc")

# Runs `gainfpn estimate` with one pipeline step slowed down and announced by
# a file, so that the signal arrives inside that step.
DRIVER = textwrap.dedent(
    """
    import signal, sys, time
    from pathlib import Path
    import gainfpn_cli.solving as solving
    import gainfpn_cli.outputs as outputs
    from gainfpn_cli.cli import main

    # Ctrl-C as a terminal delivers it to a foreground command: a suite started as a background
    # job of a non-interactive shell hands SIGINT down ignored, and Python keeps it ignored.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    stage, ready = sys.argv[1], Path(sys.argv[2])
    if stage == "solve":
        solve = solving.solve_planes
        def announced(*args, **kwargs):
            ready.touch()
            return solve(*args, **kwargs)
        solving.solve_planes = announced
    else:
        write = outputs.write_exr
        def slow(path, *args, **kwargs):
            write(path, *args, **kwargs)
            if "corrected" in str(path):
                ready.touch()
                time.sleep(60)
        outputs.write_exr = slow
    main(sys.argv[3:])
    """
)


@pytest.fixture(scope="module")
def burst_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("interrupt") / "sim"
    save_burst(simulate_burst(shape=(360, 480), n_frames=8, seed=2), folder, fmt="exr")
    return folder


def _children(pid: int) -> set[int]:
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


@pytest.fixture(scope="module")
def small_burst_dir(tmp_path_factory):
    """A burst quick to estimate, for a signal during the write."""
    folder = tmp_path_factory.mktemp("interrupt") / "small"
    save_burst(simulate_burst(shape=(96, 128), n_frames=6, seed=2), folder, fmt="exr")
    return folder


@pytest.mark.parametrize("stage, signum, status", [("solve", signal.SIGINT, 130), ("solve", signal.SIGTERM, 143),
                                                   ("write", signal.SIGTERM, 143)])
def test_a_signal_leaves_nothing_behind(request, tmp_path, stage, signum, status):
    ready, out, config = tmp_path / "ready", tmp_path / "out", tmp_path / "tiles.yaml"
    # 12 tiles: the pool has work for both processes; before the write, the quickest solve
    tuned = "" if stage == "solve" else "  robust_rounds: 0\n  partners: 1\n"
    config.write_text("solver:\n  tile: 128\n" + tuned)
    burst = request.getfixturevalue("burst_dir" if stage == "solve" else "small_burst_dir")
    command = [sys.executable, "-c", DRIVER, stage, str(ready), "estimate", str(burst), "-o", str(out),
               "--quiet", "--workers", "2", "-c", str(config)]
    proc = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not ready.exists():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the step never started"
        time.sleep(0.05)
    time.sleep(1.0)  # inside the step (the solve of this burst takes several seconds on 2 workers)
    workers = _children(proc.pid) if stage == "solve" else set()
    assert proc.poll() is None, "finished before the signal: make the burst larger"
    os.kill(proc.pid, signum)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == status, err
    assert err.strip().splitlines()[-1].startswith("Error: ") and "nothing was written" in err
    assert "Traceback" not in err
    assert not out.exists()
    assert not list(tmp_path.glob(".out.*")), "staging directory left behind"
    if stage == "solve":
        assert len(workers) >= 2  # the pool's processes (and its resource tracker) were running
        time.sleep(0.5)
        assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()
                    and "Z" not in Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]]
