"""Effective configuration: frozen dataclasses, strict YAML loading.

Precedence is defaults < preset < YAML file < command-line flags. Every key is
checked where it is read, and an error names the source and the key's path::

    my.yaml: solver.block_size: must be a positive integer, got -16

The dataclass defaults below are the documentation; ``configs/default.yaml``
mirrors them with a one-line comment per key (a test keeps the two equal).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Mapping

import yaml

from .errors import ConfigError
from .motion import ALL_MODELS
from .solve import FPN_MODELS

# --------------------------------------------------------------------------
# value checks: each takes the raw YAML value and returns the converted value
# or raises ValueError("must be ..., got ...")


def _got(value: Any) -> str:
    return f"got {value!r}"


def _int(value: Any, *, minimum: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"must be {what}, {_got(value)}")
    return value


def positive_int(value: Any) -> int:
    return _int(value, minimum=1, what="a positive integer")


def non_negative_int(value: Any) -> int:
    return _int(value, minimum=0, what="a non-negative integer")


def non_negative_float(value: Any) -> float:
    # YAML 1.1 reads `1e-4` (no dot) as a string; accept it, the intent is clear.
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"must be a non-negative number, {_got(value)}")
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"must be a finite non-negative number, {_got(value)}")
    return float(value)


def boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"must be true or false, {_got(value)}")
    return value


def choice(*options: str) -> Callable[[Any], str]:
    def check(value: Any) -> str:
        if value not in options:
            raise ValueError(f"must be one of {', '.join(options)}, {_got(value)}")
        return value

    return check


def optional(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    def check_optional(value: Any) -> Any:
        return None if value is None else check(value)

    return check_optional


def positive_float(value: Any) -> float:
    value = non_negative_float(value)
    if value <= 0:
        raise ValueError(f"must be a positive number, {_got(value)}")
    return value


def gain_range(value: Any) -> tuple[float, float]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not 0 < value[0] < 1 < value[1] or not math.isfinite(value[1])):
        raise ValueError(f"must be [low, high] with 0 < low < 1 < high, {_got(value)}")
    return (float(value[0]), float(value[1]))


def path_string(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"must be a file path, {_got(value)}")
    return value


def _key(default: Any, check: Callable[[Any], Any], doc: str) -> Any:
    return field(default=default, metadata={"check": check, "doc": doc})


# --------------------------------------------------------------------------
# sections

#: EXR compressions that round-trip float32 exactly (pxr24, dwaa and dwab are lossy; docs/method.md section 14).
LOSSLESS_COMPRESSIONS = ("none", "zip", "zips", "piz", "rle", "zstd")


@dataclass(frozen=True)
class InputConfig:
    reference: int = _key(0, non_negative_int, "index of the reference frame, after sorting by name")
    saturation: float | None = _key(
        None,
        optional(non_negative_float),
        "DN (after black level) at or above which a pixel is clipped; null = from the file",
    )
    dark: str | None = _key(None, optional(path_string), "master dark frame subtracted first; null = none")
    defects: bool = _key(
        True, boolean, "find defective photosites (hot, dead, stuck) from the burst, and hot ones from the dark "
        "frame; leave them out of the solve, write k = 1 and confidence 0 there"
    )
    defects_latent: bool = _key(
        True, boolean, "on a RAW CFA burst of 6+ frames, test the likeliest hot photosites again against a latent "
        "scene fitted without them: more of them found on sharp scenes, at about 3x the defect search's time"
    )
    exposure: str = _key(
        "per-frame",
        choice("per-frame", "fixed"),
        "per-frame: measure each frame's exposure against the reference along the motion and compare frames "
        "at equal exposure (auto-exposure steps, flickering light); fixed: take every frame as exposed alike",
    )


@dataclass(frozen=True)
class MotionConfig:
    model: str = _key(
        "auto",
        choice("auto", *ALL_MODELS),
        "motion model: a global warp, a homography plus a smooth field (rolling: per row, for a rolling "
        "shutter; mesh: over the frame), or layers (a homography per scene layer: a near object's parallax, an "
        "object moving on its own); auto picks the one with the lowest GRIC (robust information criterion)",
    )
    # 0 by default, 1 in the accurate preset: a round halves the worst small-frame motion error of a
    # smooth scene for twice the solve time (docs/method.md, Measured choices).
    refine_rounds: int = _key(
        0, non_negative_int, "estimate k, correct the frames, re-estimate motion and solve again this many times"
    )
    mask_moving: bool = _key(
        True, boolean, "leave out of the solve the pixels that do not follow the global motion (moving objects)"
    )


@dataclass(frozen=True)
class SolverConfig:
    method: str = _key(
        "auto", choice("auto", "accurate", "paper", "scene"),
        "auto (scene where the burst is aliased, else accurate), accurate (pairwise comparisons), paper (the "
        "published form) or scene (one forward model of the burst with a super-resolved latent scene)",
    )
    block_size: int = _key(5, positive_int, "side of the square blocks of frame 0, in pixels")
    lam: float = _key(0.0, non_negative_float, "ridge weight of lam * ||k - 1||^2")
    interpolation: str = _key(
        "lanczos4", choice("bilinear", "cubic", "lanczos4"),
        "kernel of the accurate method (the paper method is bilinear by definition)",
    )
    anchors: str = _key(
        "all", choice("all", "reference"), "accurate method: every frame anchors comparisons, or only the reference"
    )
    partners: int = _key(
        8, non_negative_int,
        "accurate method: frames each anchor is compared with, nearest first; 0 = all (cost grows with frames^2)",
    )
    rtol: float = _key(1e-3, positive_float, "accurate method: relative tolerance of the iterative solve")
    gauge_sigma: float = _key(8.0, positive_float, "accurate method: gain structure wider than this (px) is gauged to 1")
    tile: int = _key(512, positive_int, "accurate method: tiles of this side (px) are solved in parallel")
    scene_scale: int = _key(2, positive_int, "scene method: latent scene samples per pixel pitch, on each axis")
    scene_steps: int = _key(2, positive_int, "scene method: Gauss-Newton steps")
    # 32, not the accurate method's 8: the scene model sees the middle band, and the gauge's removal of a
    # white FPN's own low band is then its largest error (noise-free 240x320x8 dead leaves: 0.188 % at 8,
    # 0.077 % at 32, 0.062 % with none).
    scene_gauge_sigma: float = _key(
        32.0, positive_float, "scene method: gain structure wider than this (px) is gauged to 1"
    )
    robust_rounds: int = _key(
        2, non_negative_int, "accurate method: re-solves that down-weight comparisons that do not fit"
    )
    phase_weights: str = _key(
        "auto", choice("auto", "all", "none"),
        "accurate method: weight each comparison by how well interpolation predicts it where its sample falls "
        "between pixels (robust rounds); auto = on the planes of a RAW mosaic, which are aliased",
    )
    fpn_model: str = _key(
        "auto", choice("auto", *FPN_MODELS),
        "accurate method: gain FPN model; auto picks the one with the lowest AIC",
    )
    min_snr: float = _key(
        5.0, non_negative_float,
        "photosites whose mean reading is less than this many times its noise (measured on the burst) are not "
        "solved: k = 1, confidence 0 (0 = every photosite above black)",
    )
    workers: int = _key(
        2, positive_int, "processes that solve blocks in parallel, and the defect search's threads and processes"
    )
    max_condition: float = _key(
        1e4, positive_float, "a block system worse conditioned than this gets the smallest ridge that fixes it"
    )
    gain_range: tuple = _key(
        (0.5, 2.0), gain_range, "gains outside [low, high] are not physical: such blocks are left unestimated"
    )


@dataclass(frozen=True)
class OutputConfig:
    compression: str = _key("zip", choice(*LOSSLESS_COMPRESSIONS), "EXR compression (lossless ones only)")
    corrected: bool = _key(True, boolean, "write every corrected input frame")
    repair: bool = _key(
        True, boolean, "in corrected frames, replace defective photosites by the mean of their healthy neighbours "
        "of the same colour"
    )
    preview: bool = _key(True, boolean, "write preview.png of the gain map")
    holdout: bool = _key(
        True, boolean, "fit without the last frame and check, plane by plane, that k helps on it by more than the "
        "check's noise; where not, write k = 1 and warn"
    )


@dataclass(frozen=True)
class Config:
    input: InputConfig = field(default_factory=InputConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


# --------------------------------------------------------------------------
# loading


def _unknown_key(key: Any, known: list[str]) -> str:
    close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else f" (known keys: {', '.join(known)})"
    return f"unknown key{hint}"


def _section_type(f: dataclasses.Field) -> type | None:
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
    return type(default) if dataclasses.is_dataclass(default) else None


def _merge(obj: Any, data: Any, *, source: str, prefix: str = "") -> Any:
    """Return a copy of dataclass ``obj`` with the mapping ``data`` applied, checked."""
    where = f"{source}: {prefix.rstrip('.') or '<top level>'}"
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: must be a mapping of keys, got {type(data).__name__}")
    known = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in data.items():
        if key not in known:
            raise ConfigError(f"{source}: {prefix}{key}: {_unknown_key(key, list(known))}")
        f = known[key]
        if _section_type(f) is not None:
            changes[key] = _merge(getattr(obj, key), value, source=source, prefix=f"{prefix}{key}.")
            continue
        try:
            changes[key] = f.metadata["check"](value)
        except ValueError as exc:
            raise ConfigError(f"{source}: {prefix}{key}: {exc}") from None
    return dataclasses.replace(obj, **changes)


def load_yaml(text: str, *, source: str):
    """``yaml.safe_load`` of ``text``; a syntax error becomes a one-line :class:`ConfigError` naming
    ``source`` and the line."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" (line {mark.line + 1})" if mark is not None else ""
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())  # one line, whatever YAML says
        raise ConfigError(f"{source}: not valid YAML{at}: {problem}") from None


def parse_config(text: str, *, source: str = "<config>", base: Config | None = None) -> Config:
    """Apply YAML ``text`` on top of ``base`` (default: the built-in defaults)."""
    data = load_yaml(text, source=source)
    return _merge(base or Config(), {} if data is None else data, source=source)


def preset_names() -> list[str]:
    """Names of the presets shipped in ``configs/`` (besides ``default``)."""
    files = resources.files("gainfpn_cli.configs").iterdir()
    return sorted(p.name[:-5] for p in files if p.name.endswith(".yaml") and p.name != "default.yaml")


def preset_text(name: str) -> str:
    """YAML text of a shipped preset (``default``, ``fast``, ...)."""
    names = preset_names() + ["default"]
    if name not in names:
        raise ConfigError(f"preset {name!r}: {_unknown_key(name, names).replace('key', 'preset')}")
    return (resources.files("gainfpn_cli.configs") / f"{name}.yaml").read_text(encoding="utf-8")


def load_config(
    path: str | Path | None = None,
    *,
    preset: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    base: Config | None = None,
) -> Config:
    """Effective config: ``base`` (default: the defaults) < ``preset`` < YAML file ``path`` < ``overrides``.

    ``overrides`` maps dotted keys (``"solver.block_size"``) to values; keys
    whose value is None are skipped (a flag that was not given).
    """
    cfg = base or Config()
    if preset is not None:
        cfg = parse_config(preset_text(preset), source=f"preset {preset}", base=cfg)
    if path is not None:
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read config: {exc.strerror or exc}") from None
        cfg = parse_config(text, source=str(path), base=cfg)
    nested: dict[str, Any] = {}
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        *parents, leaf = dotted.split(".")
        node = nested
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return _merge(cfg, nested, source="command line") if nested else cfg


def config_dict(cfg: Config) -> dict:
    """The config as plain nested dicts and lists (for JSON and YAML)."""
    return _plain(dataclasses.asdict(cfg))


def dump_config(cfg: Config) -> str:
    """YAML text that :func:`parse_config` reads back to an equal object."""
    return yaml.safe_dump(config_dict(cfg), sort_keys=False)


def _plain(value: Any) -> Any:
    """Tuples become lists, so the YAML holds no Python-specific tags."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def key_docs(cfg: Config | None = None) -> dict[str, str]:
    """Dotted key -> one-line description, for documentation and tests."""
    cfg = cfg or Config()
    docs = {}
    for section in dataclasses.fields(cfg):
        for f in dataclasses.fields(getattr(cfg, section.name)):
            docs[f"{section.name}.{f.name}"] = f.metadata["doc"]
    return docs
