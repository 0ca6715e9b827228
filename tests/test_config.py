import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gainfpn_cli.config import (
    LOSSLESS_COMPRESSIONS,
    Config,
    dump_config,
    key_docs,
    load_config,
    parse_config,
    preset_names,
    preset_text,
)
from gainfpn_cli.errors import ConfigError

DEFAULT_YAML = Path(__file__).parents[1] / "configs" / "default.yaml"


def test_default_yaml_mirrors_dataclass_defaults():
    assert load_config(DEFAULT_YAML) == Config()
    assert parse_config(preset_text("default")) == Config()


def test_default_yaml_comments_every_key():
    lines = [ln for ln in DEFAULT_YAML.read_text().splitlines() if re.match(r"^\s+\w+:", ln)]
    keys = {ln.split(":")[0].strip() for ln in lines}
    assert keys == {k.split(".")[1] for k in key_docs()}
    for line in lines:
        assert "#" in line, f"key without a comment in default.yaml: {line!r}"


def test_every_preset_loads():
    for name in preset_names():
        assert isinstance(load_config(preset=name), Config)


def test_error_names_file_key_and_value(tmp_path):
    text = "solver:\n  block_size: -16\n"
    with pytest.raises(ConfigError, match=r"^my\.yaml: solver\.block_size: must be a positive integer, got -16$"):
        parse_config(text, source="my.yaml")
    cfg = tmp_path / "my.yaml"
    cfg.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(f"{cfg}: solver.block_size: must be a positive integer")):
        load_config(cfg)


@pytest.mark.parametrize(
    "text, message",
    [
        ("solver: {blok_size: 3}", r"solver\.blok_size: unknown key \(did you mean 'block_size'\?\)"),
        ("sovler: {}", r"sovler: unknown key \(did you mean 'solver'\?\)"),
        ("solver: {zzz: 1}", r"solver\.zzz: unknown key \(known keys: method, block_size"),
        ("solver: {block_size: true}", r"solver\.block_size: must be a positive integer, got True"),
        ("solver: {block_size: 2.5}", r"solver\.block_size: must be a positive integer, got 2\.5"),
        ("solver: {lam: -1}", r"solver\.lam: must be a finite non-negative number, got -1"),
        ("solver: {lam: .nan}", r"solver\.lam: must be a finite non-negative number"),
        ("solver: {lam: abc}", r"solver\.lam: must be a non-negative number, got 'abc'"),
        ("solver: {method: fancy}", r"solver\.method: must be one of auto, accurate, paper, scene, got 'fancy'"),
        ("output: {compression: dwaa}", r"output\.compression: must be one of none, zip"),
        ("output: {corrected: yes please}", r"output\.corrected: must be true or false"),
        ("solver: 3", r"solver: must be a mapping of keys, got int"),
        ("solver: {gain_range: [2, 0.5]}", r"solver\.gain_range: must be \[low, high\] with 0 < low < 1 < high"),
        ("solver: {max_condition: 0}", r"solver\.max_condition: must be a positive number, got 0\.0"),
        ("- a\n- b", r"<top level>: must be a mapping of keys, got list"),
        ("solver: {block_size: [1", r"not valid YAML \(line \d+\)"),
    ],
)
def test_strict_loading(text, message):
    with pytest.raises(ConfigError, match=r"^cfg\.yaml: " + message):
        parse_config(text, source="cfg.yaml")


def test_lossy_compression_is_not_offered():
    assert not {"pxr24", "dwaa", "dwab", "b44"} & set(LOSSLESS_COMPRESSIONS)


def test_exponent_without_dot_is_read_as_a_number():
    # YAML 1.1 reads 1e-4 as a string; users write it anyway.
    assert parse_config("solver: {lam: 1e-4}").solver.lam == 1e-4


def test_empty_file_gives_defaults():
    assert parse_config("") == Config()
    assert parse_config("# nothing\n") == Config()


def test_precedence_defaults_preset_file_flags(tmp_path, monkeypatch):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("solver: {block_size: 9, lam: 0.5}\noutput: {preview: false}\n")
    loaded = load_config(cfg, overrides={"solver.block_size": 3, "solver.workers": None})
    assert loaded.solver.block_size == 3  # flag beats file
    assert loaded.solver.lam == 0.5  # file beats default
    assert loaded.output.preview is False
    assert loaded.solver.workers == Config().solver.workers  # a flag not given changes nothing
    # a preset sits between the defaults and the file
    monkeypatch.setattr("gainfpn_cli.config.preset_text", lambda name: "solver: {lam: 7.0, workers: 1}")
    monkeypatch.setattr("gainfpn_cli.config.preset_names", lambda: ["p"])
    loaded = load_config(cfg, preset="p")
    assert (loaded.solver.lam, loaded.solver.workers) == (0.5, 1)


def test_flag_errors_name_the_command_line():
    with pytest.raises(ConfigError, match=r"^command line: solver\.workers: must be a positive integer, got 0$"):
        load_config(overrides={"solver.workers": 0})


def test_unknown_preset_and_unreadable_file(tmp_path):
    with pytest.raises(ConfigError, match=r"preset 'fsat'"):
        load_config(preset="fsat")
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read config"):
        load_config(tmp_path / "nope.yaml")


# every key must have a strategy here: a new key fails this test until added
STRATEGIES = {
    "input.reference": st.integers(0, 1000),
    "input.saturation": st.none() | st.floats(0, 1e9, allow_nan=False),
    "input.dark": st.none() | st.text(min_size=1, max_size=20),
    "input.defects": st.booleans(),
    "input.defects_latent": st.booleans(),
    "input.exposure": st.sampled_from(["per-frame", "fixed"]),
    "motion.model": st.sampled_from(["auto", "translation", "affine", "homography", "rolling", "mesh"]),
    "motion.refine_rounds": st.integers(0, 5),
    "motion.mask_moving": st.booleans(),
    "solver.robust_rounds": st.integers(0, 5),
    "solver.min_snr": st.floats(0, 1e3, allow_nan=False),
    "output.holdout": st.booleans(),
    "output.repair": st.booleans(),
    "solver.method": st.sampled_from(["accurate", "paper", "scene"]),
    "solver.block_size": st.integers(1, 4096),
    "solver.lam": st.floats(0, 1e12, allow_nan=False),
    "solver.interpolation": st.sampled_from(["bilinear", "cubic", "lanczos4"]),
    "solver.anchors": st.sampled_from(["all", "reference"]),
    "solver.partners": st.integers(0, 64),
    "solver.rtol": st.floats(1e-8, 1.0),
    "solver.gauge_sigma": st.floats(0.1, 1e3, allow_nan=False),
    "solver.tile": st.integers(1, 10000),
    "solver.scene_scale": st.integers(1, 8),
    "solver.scene_steps": st.integers(1, 20),
    "solver.scene_gauge_sigma": st.floats(0.1, 1e3, allow_nan=False),
    "solver.fpn_model": st.sampled_from(["auto", "none", "row", "column", "column+row", "pixel"]),
    "solver.phase_weights": st.sampled_from(["auto", "all", "none"]),
    "solver.workers": st.integers(1, 64),
    "solver.max_condition": st.floats(1e-3, 1e300, allow_nan=False),
    "solver.gain_range": st.tuples(st.floats(0.01, 0.99), st.floats(1.01, 100.0)),
    "output.compression": st.sampled_from(LOSSLESS_COMPRESSIONS),
    "output.corrected": st.booleans(),
    "output.preview": st.booleans(),
}


def test_strategies_cover_every_key():
    assert set(STRATEGIES) == set(key_docs())


@settings(max_examples=60, deadline=None)
@given(st.fixed_dictionaries({}, optional=STRATEGIES))
def test_dump_then_load_gives_an_equal_config(values):
    cfg = load_config(overrides=values)
    text = dump_config(cfg)
    assert parse_config(text, source="dump") == cfg
    assert "!!" not in text  # plain YAML, no Python tags
