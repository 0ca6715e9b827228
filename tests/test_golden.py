"""Golden outputs: a small mono EXR burst's and a small RGGB burst's k and confidence, against
arrays stored before a refactor, so that a change of structure is caught changing a result.

The arrays come from ``python tests/test_golden.py`` (run it only when a result is meant to
change, and say why in the commit). The simulated frames are stored with them: the simulator's
rendering rounds differently on another CPU (OpenCV's and NumPy's vector paths), and a reading
one count off changes k everywhere its trajectories reach (measured: up to 0.9 % on the mono burst
between two x86_64 machines). From the same frames the estimate is bit-identical on one machine;
another CPU may round the last bit of a float32 sum differently, hence the tolerance below.

OpenCV's kernels (the flow and the remaps) are compiled for several vector extensions and pick
the widest the CPU has, which rounds differently enough to move the estimate (measured on the same
stored frames, an AVX2-only AMD EPYC against arrays written on a CPU that was not recorded: k
2.6e-4 RMS, 7.5e-3 at most on the mono burst; with OpenCV's optimisations off 1.9e-5 RMS; an
AVX-512 AMD EPYC against the AVX2 arrays: 7.3e-3 at most, which OPENCV_CPU_DISABLE,
NPY_DISABLE_CPU_FEATURES, NUMBA_CPU_NAME and OPENCV_IPP did not take away). So arrays are stored
for each kind of CPU met (a folder per :func:`cpu_kind`), all from the same frames, and the
estimate must match one set; where none matches and none was written on this kind of CPU, the test
is skipped, saying so. When a result is meant to change, the sets of other CPUs are stale: remove
them and write each kind's on its own machine.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gainfpn_cli.config import load_config
from gainfpn_cli.pipeline import estimate, load_burst
from gainfpn_cli.sim.sensor import PRESETS
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst

GOLDEN = Path(__file__).parent / "golden"
#: The bursts, seeded; the RGGB one is a 12-bit DNG, so RAW reading, the green lattice, the per-plane
#: gauge and the halves' calibration are all in the path (7 frames: a mosaic fitted on fewer than 6 is
#: written k = 1, checking.short_mosaic).
BURSTS = {
    "mono_exr": dict(shape=(96, 128), n_frames=6, seed=21, fmt="exr", sensor="paper"),
    "rggb_dng": dict(shape=(144, 176), n_frames=7, seed=22, fmt="dng", sensor="raw12"),
}
#: How far k and confidence may be from a stored set. float32 k near 1: 1e-6 is a few ulps (6e-8
#: each), more than a reordered sum changes, far less than any change of method (the estimate's own
#: error is ~1e-3 to 1e-2). The confidence of a short burst is calibrated by a statistic of a second
#: solve (solve/bootstrap.py), which carries a reordered sum further: the scene model's products
#: summed in another order (2e-7 of a product) moved it by up to 1.5e-6 on the mono burst (k by
#: 2.4e-7). 1e-5 still catches sigma_k changed by 3e-5 of itself (confidence 1 / (1 + x^2) moves
#: by 2 c (1 - c) = 0.35 times x's relative change at its median 0.77).
ATOL = {"k": 1e-6, "confidence": 1e-5}


def cpu_kind() -> str:
    """The widest vector extension OpenCV dispatches to here (OpenCV's feature ids: AVX-512F 13,
    AVX2 11), which names the folder of this CPU's arrays."""
    import cv2

    return "avx512" if cv2.checkHardwareSupport(13) else "avx2" if cv2.checkHardwareSupport(11) else "baseline"


def stored_arrays(name: str) -> list[Path]:
    """Every stored set of ``name``'s arrays (one per kind of CPU)."""
    return sorted(GOLDEN.glob(f"*/{name}.npz"))


def run(name: str, folder: Path, frames: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The burst ``name`` (its ``frames`` instead of the simulator's, if given) written, read and
    estimated: its frames, k and confidence."""
    spec = dict(BURSTS[name])
    fmt, sensor = spec.pop("fmt"), spec.pop("sensor")
    burst = simulate_burst(sensor=PRESETS[sensor], **spec)
    if frames is not None:
        burst = dataclasses.replace(burst, frames=frames)
    save_burst(burst, folder, fmt=fmt)
    cfg = load_config(overrides={"solver.workers": 1})
    result = estimate(load_burst([folder], cfg), cfg)
    return {"frames": burst.frames, "k": result.k, "confidence": result.confidence}


@pytest.mark.parametrize("name", sorted(BURSTS))
def test_k_and_confidence_are_those_stored(name, tmp_path):
    paths = stored_arrays(name)
    assert paths, f"no stored arrays for {name}: write them with python tests/test_golden.py"
    now = run(name, tmp_path / name, np.load(paths[0])["frames"])
    off = {}
    for path in paths:
        stored = np.load(path)
        assert np.array_equal(stored["frames"], np.load(paths[0])["frames"]), path  # one input for all
        assert all(now[key].shape == stored[key].shape for key in ("k", "confidence")), path
        off[path.parent.name] = {key: float(np.abs(now[key].astype(np.float64) - stored[key]).max())
                                 for key in ("k", "confidence")}
    matched = any(all(o[key] <= ATOL[key] for key in ATOL) for o in off.values())
    if not matched and cpu_kind() not in off:  # another kind of CPU rounds the flow and the remaps differently
        pytest.skip(f"{name}: no arrays stored for this kind of CPU ({cpu_kind()}; stored: {', '.join(off)}): "
                    "write them here with python tests/test_golden.py")
    assert matched, f"{name}: k or confidence off every stored set by (at most) {off}"


if __name__ == "__main__":  # write this CPU's arrays again, from the frames stored for any CPU
    import tempfile

    for name in BURSTS:
        stored = stored_arrays(name)
        frames = np.load(stored[0])["frames"] if stored else None
        path = GOLDEN / cpu_kind() / f"{name}.npz"
        path.parent.mkdir(exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            np.savez_compressed(path, **run(name, Path(tmp) / name, frames))
        print("wrote", path)
