"""Fuzzing (issue 7): the readers and the config loader either succeed or
raise their one user-facing error, whatever bytes or YAML they are given.
CI runs 60 fixed examples per test (about 1 s); a longer search for new
failures: ``HYPOTHESIS_PROFILE=explore FUZZ_EXAMPLES=3000 python -m pytest
tests/test_fuzz.py`` (20 s, clean on 2026-11-22 after the two fixes it found:
a YAML error spread over two lines, OIIO error text that was not UTF-8)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from gainfpn_cli import files as io
from gainfpn_cli.config import Config, parse_config
from gainfpn_cli.errors import ConfigError, InputError
from gainfpn_cli.sim.dng import write_dng

FUZZ = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", 60)), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    io.write_exr(folder / "v.exr", {"Y": rng.random((16, 20))}, compression="zip")
    write_dng(folder / "v.dng", rng.integers(0, 4096, (16, 20)).astype(np.uint16), bits=12, cfa="RGGB",
                 black=[64] * 4, white=4095)
    return {ext: (folder / f"v.{ext}").read_bytes() for ext in ("exr", "dng")}


def _read(path) -> None:
    try:
        frame = io.read_frame(path)
    except InputError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)
        return
    assert np.isfinite(frame.data).all()


@FUZZ
@given(data=st.binary(max_size=2048), ext=st.sampled_from(["exr", "dng", "cr2", "nef"]))
def test_random_bytes(tmp_path, data, ext):
    path = tmp_path / f"f.{ext}"
    path.write_bytes(data)
    _read(path)


@FUZZ
@given(ext=st.sampled_from(["exr", "dng"]),
       edits=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.one_of(st.none(), st.floats(0, 1)))
@example(ext="exr", edits=[(0.125, 128), (0.109375, 1)], cut=None)  # OIIO's error text was not UTF-8
def test_damaged_valid_files(tmp_path, valid_files, ext, edits, cut):
    data = bytearray(valid_files[ext])
    for where, value in edits:  # overwrite bytes anywhere, header included
        data[int(where * len(data))] = value
    if cut is not None:
        data = data[: int(cut * len(data))]
    path = tmp_path / f"f.{ext}"
    path.write_bytes(bytes(data))
    _read(path)


_YAML_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=12), inner, max_size=3),
    max_leaves=8,
)
_SECTIONS = st.sampled_from(["input", "motion", "solver", "output", "bogus"])
_KEYS = st.sampled_from(["model", "lam", "block_size", "workers", "interpolation", "reference", "holdout",
                         "gain_range", "tile", "compression", "refine_rounds", "nonsense"])


def _parse(text: str) -> None:
    try:
        assert isinstance(parse_config(text, source="fuzz.yaml"), Config)
    except ConfigError as exc:
        assert str(exc).startswith("fuzz.yaml") and "\n" not in str(exc).strip()


@FUZZ
@given(st.dictionaries(_SECTIONS, st.dictionaries(_KEYS, _YAML_VALUES, max_size=4), max_size=3))
def test_config_shaped_yaml(document):
    _parse(yaml.safe_dump(document))


@FUZZ
@given(st.text(max_size=300))
def test_config_arbitrary_text(text):
    _parse(text)
