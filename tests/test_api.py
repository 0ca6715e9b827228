"""The Python entry point: gainfpn_cli.estimate / apply, on files and on arrays."""

import json

import numpy as np
import pytest

import gainfpn_cli as gainfpn
from gainfpn_cli.errors import InputError
from gainfpn_cli.files import read_frame
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    folder = tmp_path_factory.mktemp("api") / "burst"
    burst = simulate_burst(shape=(96, 128), n_frames=6, seed=8)
    save_burst(burst, folder, fmt="exr")
    return folder, burst


def test_files_and_the_same_frames_as_an_array_give_the_same_map(sim, tmp_path):
    folder, burst = sim
    from_files = gainfpn.estimate(folder, solver__workers=1)
    frames = np.stack([read_frame(folder / f"frame_{t:03d}.exr").data for t in range(6)])
    from_array = gainfpn.estimate(frames, saturation=burst.saturation, config=from_files.config)
    np.testing.assert_array_equal(from_files.k, from_array.k)
    np.testing.assert_array_equal(from_files.confidence, from_array.confidence)
    assert from_files.report.status == "accepted" and 4.0 < from_files.report.prnu_percent.total < 6.0
    assert len(from_files.report.inputs) == 6 and from_array.report.inputs == ()
    written = from_array.write(tmp_path / "out")
    assert (tmp_path / "out" / "corrected" / "frame_000.exr").is_file()
    assert json.loads((tmp_path / "out" / "report.json").read_text())["status"] == written.report.status


def test_presets_configs_and_overrides_compose(sim, tmp_path):
    folder, _ = sim
    config = tmp_path / "c.yaml"
    config.write_text("solver: {partners: 2}\n")
    result = gainfpn.estimate(str(folder / "frame_*.exr"), preset="fast", config=config, solver__workers=1)
    assert result.config.solver.partners == 2 and result.config.solver.workers == 1
    assert result.config.output.compression == "none"  # from the fast preset


def test_apply_from_python_equals_the_estimates_corrected_frames(sim, tmp_path):
    folder, _ = sim
    gainfpn.estimate(folder, solver__workers=1).write(tmp_path / "est")
    written = gainfpn.apply(folder, gain_map=tmp_path / "est" / "gain_map.exr", out_dir=tmp_path / "applied")
    assert len(written) == 6
    for path in written:
        np.testing.assert_array_equal(read_frame(path).data, read_frame(tmp_path / "est" / "corrected" / path.name).data)


def test_an_array_of_the_wrong_shape_is_refused():
    with pytest.raises(InputError, match="frames must have shape"):
        gainfpn.estimate(np.zeros((4, 8)))
