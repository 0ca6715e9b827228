import os

import numpy as np
import pytest
import rawpy
from helpers import _write_raw_exr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gainfpn_cli import files as io
from gainfpn_cli.errors import InputError
from gainfpn_cli.sim.dng import write_dng
from gainfpn_cli.sim.scenes import read_scene


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    hnp.arrays(
        np.float32,
        hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=24),
        elements=st.floats(allow_nan=False, allow_infinity=False, width=32),
    ),
    st.sampled_from(["none", "zip", "zips", "piz", "rle", "zstd"]),
)
def test_exr_float32_round_trip_is_exact(tmp_path, pixels, compression):
    path = tmp_path / "rt.exr"
    io.write_exr(path, {"Y": pixels, "confidence": -pixels}, compression=compression)
    planes, _ = io.read_exr_planes(path)
    assert planes["Y"].dtype == np.float32
    np.testing.assert_array_equal(planes["Y"], pixels)
    np.testing.assert_array_equal(planes["confidence"], -pixels)
    frame = io.read_frame(path)
    assert frame.info.channels == ("Y",) and frame.data.shape == pixels.shape + (1,)
    np.testing.assert_array_equal(frame.data[:, :, 0], pixels)


def test_exr_metadata_round_trip(tmp_path):
    config_text = "solver:\n  lam: 0.1234567890123\n  block_size: 5\n"
    path = tmp_path / "m.exr"
    io.write_exr(path, {"Y": np.ones((4, 5))}, metadata={"gainfpn:config": config_text, "gainfpn:inputs": '["a.exr"]'})
    _, attrs = io.read_exr_planes(path)
    assert attrs["gainfpn:config"] == config_text  # exact: numbers kept as text
    assert attrs["gainfpn:inputs"] == '["a.exr"]'


def test_exr_frame_attributes_come_back(tmp_path):
    path = tmp_path / "f.exr"
    io.write_exr(path, {"Y": np.zeros((6, 8))}, metadata={io.ATTR_CFA: "GRBG", io.ATTR_SATURATION: 4095.0})
    info = io.read_frame(path).info
    assert (info.kind, info.shape, info.cfa, info.saturation) == ("exr", (6, 8), "GRBG", 4095.0)


def test_half_rgb_exr_reads_exactly(tmp_path, rng):
    values = rng.integers(0, 2048, size=(10, 12, 3)).astype(np.float16)  # integers < 2048 are exact in half
    _write_raw_exr(tmp_path / "h.exr", values, ["R", "G", "B"], fmt="half")
    frame = io.read_frame(tmp_path / "h.exr")
    assert frame.info.channels == ("R", "G", "B") and frame.info.source_type == "half"
    np.testing.assert_array_equal(frame.data, values.astype(np.float32))


def test_exr_without_usable_channel(tmp_path):
    _write_raw_exr(tmp_path / "az.exr", np.zeros((4, 4, 2), np.float32), ["A", "Z"])
    with pytest.raises(InputError, match=r"az\.exr: no usable channel \(want Y, or R G B, or a single channel; has A, Z\)"):
        io.read_frame(tmp_path / "az.exr")


def test_nan_pixels_are_refused(tmp_path):
    pixels = np.ones((5, 7), np.float32)
    pixels[2, 3] = np.nan
    pixels[4, 0] = np.inf
    io.write_exr(tmp_path / "n.exr", {"Y": pixels})
    with pytest.raises(InputError, match=r"n\.exr: 2 NaN/Inf pixel values \(first at row 2, column 3\)"):
        io.read_frame(tmp_path / "n.exr")


def _dng(path, counts, cfa="RGGB", black=(100, 101, 102, 103), bits=12):
    write_dng(path, counts.astype(np.uint16), bits=bits, cfa=cfa, black=black, white=2**bits - 1)


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_dng_round_trip_through_rawpy(tmp_path, rng, cfa, bits):
    counts = rng.integers(200, 2**bits, size=(32, 48))
    black = (100, 101, 102, 103)
    _dng(tmp_path / "r.dng", counts, cfa=cfa, black=black, bits=bits)
    with rawpy.imread(str(tmp_path / "r.dng")) as raw:  # other tools read it: LibRaw directly
        np.testing.assert_array_equal(raw.raw_image_visible, counts)
        assert raw.white_level == 2**bits - 1
    frame = io.read_frame(tmp_path / "r.dng")
    black_map = np.tile(np.array(black, np.float32).reshape(2, 2), (16, 24))
    np.testing.assert_array_equal(frame.data[:, :, 0], counts - black_map)
    assert frame.info.cfa == cfa and frame.info.black == tuple(map(float, black))
    assert frame.info.saturation == 2**bits - 1 - 103


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("empty.exr", b"", r"empty\.exr: file is empty"),
        ("junk.exr", b"this is text, not pixels" * 10, r"junk\.exr: not a readable EXR file"),
        ("junk.dng", b"this is text, not pixels" * 10, r"junk\.dng: not a RAW file LibRaw can read"),
        ("notes.txt", b"hello" * 100, r"notes\.txt: not a RAW file LibRaw can read"),
    ],
)
def test_bad_files_get_one_clear_error(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=message):
        io.read_frame(tmp_path / name)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"gone\.exr: no such file"):
        io.read_frame(tmp_path / "gone.exr")
    with pytest.raises(InputError, match=r"gone\.dng: no such file"):
        io.read_frame(tmp_path / "gone.dng")


def test_truncated_files(tmp_path, rng):
    io.write_exr(tmp_path / "full.exr", {"Y": rng.random((64, 64))}, compression="none")
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.exr: cannot read pixels, file damaged or truncated"):
        io.read_frame(tmp_path / "cut.exr")
    _dng(tmp_path / "full.dng", rng.integers(0, 4000, (64, 64)))
    data = (tmp_path / "full.dng").read_bytes()
    (tmp_path / "cut.dng").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.dng: not a RAW file LibRaw can read \(.*damaged or truncated"):
        io.read_frame(tmp_path / "cut.dng")


def test_libraw_messages_become_part_of_the_one_error_line(tmp_path, rng, capfd):
    _dng(tmp_path / "full.dng", rng.integers(0, 4000, (64, 64)))
    data = (tmp_path / "full.dng").read_bytes()
    (tmp_path / "cut.dng").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as err:
        io.read_frame(tmp_path / "cut.dng")
    assert capfd.readouterr().err == ""  # nothing printed behind the user's back
    assert "LibRaw: Unexpected end of file" in str(err.value)


def test_wrong_extension(tmp_path, rng):
    _dng(tmp_path / "x.dng", rng.integers(0, 4000, (32, 32)))
    os.rename(tmp_path / "x.dng", tmp_path / "x.exr")
    with pytest.raises(InputError, match=r"x\.exr: not an OpenEXR file \(it reads as tiff\)"):
        io.read_frame(tmp_path / "x.exr")


def test_find_frames_sorts_and_expands(tmp_path):
    for name in ["b.exr", "a.exr", "c.dng", "notes.txt"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    assert [p.name for p in io.find_frames([tmp_path])] == ["a.exr", "b.exr", "c.dng"]
    assert [p.name for p in io.find_frames([str(tmp_path / "*.exr")])] == ["a.exr", "b.exr"]
    assert [p.name for p in io.find_frames([tmp_path / "b.exr", tmp_path / "a.exr", tmp_path / "a.exr"])] == [
        "a.exr",
        "b.exr",
    ]


@pytest.mark.parametrize(
    "spec, message",
    [
        ("nothing_here.exr", r"nothing_here\.exr: no such file or directory"),
        ("*.nomatch", r"\*\.nomatch: pattern matches no file"),
        ("sub", r"sub: directory holds no EXR or RAW frames"),
    ],
)
def test_find_frames_errors(tmp_path, monkeypatch, spec, message):
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=message):
        io.find_frames([spec])
    with pytest.raises(InputError, match="no input frames given"):
        io.find_frames([])


def test_stack_must_share_size_kind_and_cfa(tmp_path, rng):
    io.write_exr(tmp_path / "a.exr", {"Y": rng.random((8, 10))})
    io.write_exr(tmp_path / "b.exr", {"Y": rng.random((8, 12))})
    with pytest.raises(InputError, match=r"b\.exr: size 12x8 differs from a\.exr \(10x8\)"):
        io.read_stack(io.find_frames([tmp_path / "a.exr", tmp_path / "b.exr"]))
    io.write_exr(tmp_path / "c.exr", {"Y": rng.random((8, 10))}, metadata={io.ATTR_CFA: "RGGB"})
    with pytest.raises(InputError, match=r"c\.exr: CFA layout RGGB differs from a\.exr \(not stated\)"):
        io.read_stack(io.find_frames([tmp_path / "a.exr", tmp_path / "c.exr"]))
    _dng(tmp_path / "d.dng", rng.integers(0, 4000, (32, 32)))
    with pytest.raises(InputError, match=r"d\.dng: file type raw differs from a\.exr \(exr\)"):
        io.read_stack(io.find_frames([tmp_path / "a.exr", tmp_path / "d.dng"]))
    _dng(tmp_path / "e.dng", rng.integers(0, 4000, (32, 32)), cfa="BGGR")
    with pytest.raises(InputError, match=r"e\.dng: CFA layout BGGR differs from d\.dng \(RGGB\)"):
        io.read_stack(io.find_frames([tmp_path / "d.dng", tmp_path / "e.dng"]))


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.exr"
    io.write_exr(target, {"Y": np.ones((3, 3))})
    before = target.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with io.atomic_output(target) as tmp:
            tmp.write_bytes(b"half a file")
            raise KeyboardInterrupt
    assert target.read_bytes() == before  # the old result is intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.exr"]  # no temporary left


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_outputs_follow_the_umask(tmp_path, umask):
    saved = os.umask(umask)
    try:
        io.write_text(tmp_path / "t.txt", "hi")
        io.write_exr(tmp_path / "t.exr", {"Y": np.zeros((4, 4), np.float32)})
    finally:
        os.umask(saved)
    for name in ("t.txt", "t.exr"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask


def test_unwritable_directory(tmp_path):
    with pytest.raises(InputError, match=r"missing_dir/o\.exr: cannot write here"):
        io.write_exr(tmp_path / "missing_dir" / "o.exr", {"Y": np.ones((2, 2))})


def test_write_exr_checks_planes(tmp_path):
    with pytest.raises(ValueError, match="one shape"):
        io.write_exr(tmp_path / "x.exr", {"Y": np.ones((2, 2)), "Z": np.ones((2, 3))})


def test_read_scene_linearises_8bit(tmp_path):
    import cv2

    img = np.full((30, 40), 128, np.uint8)
    cv2.imwrite(str(tmp_path / "s.png"), img)
    scene = read_scene(tmp_path / "s.png")
    assert scene.shape == (30, 40)
    np.testing.assert_allclose(scene, (128 / 255) ** 2.2, rtol=1e-5)


def test_staged_outputs_are_all_or_nothing(tmp_path):
    from gainfpn_cli import outdir

    out = tmp_path / "out"

    def plan(*names):
        return outdir.prepare(out, command="apply", names=names, overwrite=True)

    with outdir.staged(plan("a.txt")) as tmp:
        (tmp / "a.txt").write_text("first")
    assert (out / "a.txt").read_text() == "first"
    with pytest.raises(KeyboardInterrupt):
        with outdir.staged(plan("b.txt")) as tmp:
            (tmp / "b.txt").write_text("half")
            raise KeyboardInterrupt
    assert sorted(p.name for p in out.iterdir()) == [outdir.MANIFEST, "a.txt"]  # the earlier results are intact
    with outdir.staged(plan("c.txt")) as tmp:
        (tmp / "c.txt").write_text("second")
    # the command's earlier output is replaced, never mixed with the new one
    assert sorted(p.name for p in out.iterdir()) == [outdir.MANIFEST, "c.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging left
