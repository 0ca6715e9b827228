"""Bad input and faults through the command line (issue 7): one line naming
the file, frame or key and what was expected, exit status 1 (2 for click's
usage errors), no traceback, and nothing left in or beside OUT. The readers'
own cases are in test_io.py, the config loader's in test_config.py."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import _write_raw_exr  # the gainfpn writer refuses non-finite pixels itself

from gainfpn_cli import files as io
from gainfpn_cli.cli import main
from gainfpn_cli.errors import InputError
from gainfpn_cli.sim.dng import write_dng
from gainfpn_cli.sim.sensor import PRESETS, with_overrides
from gainfpn_cli.sim.simulate import simulate_burst
from gainfpn_cli.sim.truth import save_burst


@pytest.fixture(scope="module")
def good_burst(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad") / "burst"
    save_burst(simulate_burst(shape=(64, 80), n_frames=4, seed=5), folder, fmt="exr")
    return folder


@pytest.fixture()
def burst(good_burst, tmp_path):
    """A fresh copy of a good 4-frame burst, to spoil."""
    folder = tmp_path / "burst"
    folder.mkdir()
    for path in good_burst.glob("frame_*.exr"):
        (folder / path.name).write_bytes(path.read_bytes())
    return folder


def _estimate(inputs, out, *extra):
    return CliRunner().invoke(main, ["estimate", *map(str, inputs), "-o", str(out), "--quiet", "--workers", "1",
                                     *extra])


def _assert_refused(result, out, *needles, status=1):
    assert result.exit_code == status, result.output
    lines = result.output.strip().splitlines()
    assert "Traceback" not in result.output and not isinstance(result.exception, (TypeError, ValueError))
    if status == 1:
        assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    for needle in needles:
        assert needle in result.output, result.output
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}.*")), "staging left behind"


def _spoil(folder, how):
    target = folder / "frame_002.exr"
    data = target.read_bytes()
    if how == "corrupt":
        target.write_bytes(data[:400] + bytes(range(256)) * 8 + data[400 + 2048:])
    elif how == "truncated":
        target.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        target.write_bytes(b"")
    elif how == "text":
        target.write_text("exposure notes, not pixels\n" * 20)
    return target


@pytest.mark.parametrize("how, expected", [
    ("corrupt", "frame_002.exr: cannot read pixels, file damaged or truncated"),
    ("truncated", "frame_002.exr: cannot read pixels, file damaged or truncated"),
    ("empty", "frame_002.exr: file is empty"),
    ("text", "frame_002.exr: not a readable EXR file"),
])
def test_a_damaged_frame_is_named(burst, tmp_path, how, expected):
    _spoil(burst, how)
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", expected)


def test_a_raw_file_with_an_exr_name(burst, tmp_path):
    sensor = with_overrides(PRESETS["raw12"])
    raw = simulate_burst(shape=(64, 80), n_frames=1, seed=1, sensor=sensor).frames[0]
    write_dng(tmp_path / "x.dng", raw, bits=12, cfa="RGGB", black=[256] * 4, white=4095)
    (burst / "frame_002.exr").write_bytes((tmp_path / "x.dng").read_bytes())
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out",
                    "frame_002.exr: not an OpenEXR file (it reads as tiff)")


@pytest.mark.parametrize("value, word", [(np.nan, "NaN"), (np.inf, "Inf")])
def test_nan_and_inf_pixels(burst, tmp_path, value, word):
    pixels = io.read_frame(burst / "frame_001.exr").data[..., 0].copy()
    pixels[10, 20] = value
    (burst / "frame_001.exr").unlink()
    _write_raw_exr(burst / "frame_001.exr", pixels[..., None], ["Y"])
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", "frame_001.exr")
    assert word.lower() in _estimate([burst], tmp_path / "out").output.lower()


def test_mixed_sizes_and_cfa_layouts(burst, tmp_path):
    io.write_exr(burst / "frame_009.exr", {"Y": np.full((64, 81), 100.0)})
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", "frame_009.exr", "81x64")
    (burst / "frame_009.exr").unlink()
    io.write_exr(burst / "frame_009.exr", {"Y": np.full((64, 80), 100.0)}, metadata={io.ATTR_CFA: "GRBG"})
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", "frame_009.exr", "GRBG")


@pytest.mark.parametrize("blank", [0, 255])
def test_a_frame_whose_every_pixel_is_defective_is_refused_by_the_tracking(tmp_path, blank):
    # a frame read as black or as white throughout (a readout that failed): no scene to follow in it,
    # refused before the defect search (whose own guard, over 5 % of a plane, is the dark frame's test below)
    burst = simulate_burst(shape=(64, 80), n_frames=5, seed=5)
    burst.frames[2] = blank
    save_burst(burst, tmp_path / "burst", fmt="exr")
    _assert_refused(_estimate([tmp_path / "burst"], tmp_path / "out"), tmp_path / "out", "frame 2:",
                    "could be tracked")


def test_a_dark_frame_of_another_size_or_sensor(burst, tmp_path):
    io.write_exr(tmp_path / "small.exr", {"Y": np.zeros((32, 40), np.float32)})
    _assert_refused(_estimate([burst], tmp_path / "out", "--dark", str(tmp_path / "small.exr")), tmp_path / "out",
                    "small.exr: dark frame is 40x32", "the frames are 80x64")
    rng = np.random.default_rng(1)  # a tenth of its photosites hot: not this sensor's dark frame
    dark = rng.normal(0.0, 1.0, (64, 80)).astype(np.float32) + 50.0 * (rng.random((64, 80)) < 0.1)
    io.write_exr(tmp_path / "other.exr", {"Y": dark})
    _assert_refused(_estimate([burst], tmp_path / "out", "--dark", str(tmp_path / "other.exr")), tmp_path / "out",
                    "% of the photosites of plane Y read as defective", "the dark frame is not this sensor's")


def test_exr_and_raw_frames_mixed(burst, tmp_path):
    raw = simulate_burst(shape=(64, 80), n_frames=1, seed=1, sensor=PRESETS["raw12"]).frames[0]
    write_dng(burst / "frame_009.dng", raw, bits=12, cfa="RGGB", black=[256] * 4, white=4095)
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", "frame_009.dng")


def test_mixed_bit_depths(tmp_path):
    rng = np.random.default_rng(4)
    for i, bits in enumerate((12, 12, 16, 12)):
        write_dng(tmp_path / f"f{i}.dng", rng.integers(64, 4000, (64, 80)).astype(np.uint16), bits=bits,
                     cfa="RGGB", black=[64] * 4, white=2**bits - 1)
    _assert_refused(_estimate([tmp_path], tmp_path.parent / "out"), tmp_path.parent / "out",
                    "f2.dng: white level 65535", "differs from f0.dng (4095)")


def test_unusual_black_levels_are_read_from_the_file(tmp_path):
    # a different black level per CFA position, one of them 100 DN below white
    black = np.array([[60, 64], [3995, 72]])
    levels = np.tile(black, (32, 40))
    counts = np.random.default_rng(3).integers(0, 100, (64, 80)) + levels
    write_dng(tmp_path / "f.dng", counts.astype(np.uint16), bits=12, cfa="RGGB", black=black.ravel().tolist(),
                 white=4095)
    frame = io.read_frame(tmp_path / "f.dng")
    np.testing.assert_array_equal(frame.data[..., 0], counts - levels)
    assert frame.info.saturation == 4095 - 3995  # the most limiting position


def test_a_full_disk_while_writing(burst, tmp_path, monkeypatch):
    from gainfpn_cli import outputs

    write = outputs.write_exr
    calls = []

    def full(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 3:  # the gain map and a corrected frame are written, then the disk fills
            raise InputError(f"{path}: cannot write ({__import__('os').strerror(errno.ENOSPC)})")
        return write(path, *args, **kwargs)

    monkeypatch.setattr(outputs, "write_exr", full)
    _assert_refused(_estimate([burst], tmp_path / "out"), tmp_path / "out", "No space left on device")


def test_the_write_error_of_a_full_disk_names_the_file(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    class Full:
        """An ImageOutput whose writes fail as they do on a full disk."""

        @staticmethod
        def create(name):
            return Full()

        def open(self, *args):
            return True

        def write_image(self, *args):
            return False

        def close(self):
            return True

        def geterror(self):
            return "Write error: No space left on device"

    monkeypatch.setattr(oiio, "ImageOutput", Full)
    with pytest.raises(InputError, match=r"k\.exr: .*No space left on device"):
        io.write_exr(tmp_path / "k.exr", {"Y": np.ones((4, 4))})
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("text, needle", [
    ("solver:\n  lamda: 0.1\n", "solver.lamda"),
    ("solver:\n  block_size: five\n", "solver.block_size"),
    ("motion:\n  model: fancy\n", "motion.model"),
])
def test_config_errors_name_the_key(burst, tmp_path, text, needle):
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    _assert_refused(_estimate([burst], tmp_path / "out", "-c", config), tmp_path / "out", needle, "bad.yaml")


def test_usage_errors_exit_2(burst, tmp_path):
    _assert_refused(_estimate([burst], tmp_path / "out", "--workers", "0"), tmp_path / "out", "--workers", status=2)
    _assert_refused(_estimate([burst], tmp_path / "out", "--preset", "fastest"), tmp_path / "out", "--preset",
                    status=2)


def test_an_existing_output_is_not_touched(burst, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier results")
    result = _estimate([burst], out)
    assert result.exit_code == 0 and "left untouched" in result.output and "keep.txt" in result.output
    assert (out / "keep.txt").read_text() == "earlier results" and (out / "gain_map.exr").is_file()


def test_an_output_directory_that_cannot_be_created(burst, tmp_path):
    # a regular file where OUT's parent should be: refused even for root, who may write anywhere else
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file")
    result = _estimate([burst], blocker / "out")
    assert result.exit_code == 1 and len(result.output.strip().splitlines()) == 1
    assert str(blocker / "out") in result.output and "Traceback" not in result.output
    assert blocker.read_text() == "a file"
