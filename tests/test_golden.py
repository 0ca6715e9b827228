"""Golden outputs: a small mono EXR burst's and a small RGGB burst's k and confidence, against
arrays stored before a refactor, so that a change of structure is caught changing a result.

The arrays come from ``python tests/test_golden.py`` (run it only when a result is meant to
change, and say why in the commit). The simulated frames are stored with them: the simulator's
rendering rounds differently on another CPU (OpenCV's and NumPy's vector paths), and a reading
one count off changes k everywhere its trajectories reach (measured: up to 0.9 % on the mono burst
between two x86_64 machines). From the same frames the estimate is bit-identical on one machine;
another CPU may round the last bit of a float32 sum differently, hence the tolerance below.
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
#: The bursts: 6 frames each, seeded; the RGGB one is a 12-bit DNG, so RAW reading, the green
#: lattice and the per-plane gauge are all in the path.
BURSTS = {
    "mono_exr": dict(shape=(96, 128), n_frames=6, seed=21, fmt="exr", sensor="paper"),
    "rggb_dng": dict(shape=(144, 176), n_frames=6, seed=22, fmt="dng", sensor="raw12"),
}
#: float32 k near 1: 1e-6 is a few ulps (6e-8 each), more than a reordered sum changes, far less
#: than any change of method (the estimate's own error is ~1e-3 to 1e-2).
ATOL = 1e-6


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
    stored = np.load(GOLDEN / f"{name}.npz")
    now = run(name, tmp_path / name, stored["frames"])
    for key in ("k", "confidence"):
        assert now[key].shape == stored[key].shape
        np.testing.assert_allclose(now[key], stored[key], rtol=0, atol=ATOL, err_msg=f"{name}: {key}")


if __name__ == "__main__":  # write the stored arrays again
    import tempfile

    for name in BURSTS:
        with tempfile.TemporaryDirectory() as tmp:
            np.savez_compressed(GOLDEN / f"{name}.npz", **run(name, Path(tmp) / name))
        print("wrote", GOLDEN / f"{name}.npz")
