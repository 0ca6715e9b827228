"""The Python entry point: what ``gainfpn estimate`` and ``gainfpn apply`` do, for notebooks and
a lab's own pipeline code.

    import gainfpn_cli as gainfpn

    result = gainfpn.estimate("captures/*.dng", preset="balanced")
    result.report.prnu_percent.total, result.report.status     # typed (report.Report)
    corrected = result.k * frame                                # k, confidence: (H, W, C) float32
    result.write("calib/")                                      # gain_map.exr, corrected/, report.json, ...
    gainfpn.apply("stills/*.dng", gain_map="calib/gain_map.exr", out_dir="corrected/")

The command line calls these same functions.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import burst as _burst
from .config import Config, load_config
from .errors import InputError
from .outputs import Written, apply_gain_map, write_estimate
from .pipeline import estimate as _estimate
from .pipeline import load_burst
from .report import Report


@dataclass(frozen=True)
class Estimate:
    """A burst's gain map: ``k`` (multiply a frame by it to correct) and ``confidence``, both
    ``(H, W, C)`` float32, the typed :class:`report.Report`, and :meth:`write`."""

    k: np.ndarray
    confidence: np.ndarray
    report: Report
    burst: _burst.LoadedBurst = field(repr=False)
    config: Config = field(repr=False)
    defects: np.ndarray | None = None  # (H, W, C) uint8 defect codes (solve.defects.KINDS); None: not looked for

    def write(self, out_dir: str | os.PathLike, *, overwrite: bool = False, progress=None) -> Written:
        """gain_map.exr, corrected/, report.json, config.used.yaml and preview.png into ``out_dir``
        (:mod:`outdir`: only gainfpn's own names are replaced, and only with ``overwrite``)."""
        estimate = _burst.Estimate(self.k, self.confidence, self.report, self.defects)
        return write_estimate(estimate, self.burst, self.config, Path(out_dir), overwrite=overwrite, progress=progress)


def config_of(config: Config | str | os.PathLike | None = None, *, preset: str | None = None,
              **overrides) -> Config:
    """The effective config: a :class:`config.Config`, or a YAML file over ``preset``, with
    ``overrides`` given as ``section__key=value`` (``solver__workers=1``) or ``{"solver.workers": 1}``."""
    dotted = {key.replace("__", "."): value for key, value in overrides.items()}
    if isinstance(config, Config):
        return load_config(base=config, overrides=dotted) if dotted else config
    return load_config(config, preset=preset, overrides=dotted)


def estimate(inputs, *, config: Config | str | os.PathLike | None = None, preset: str | None = None,
             progress=None, executor=None, cfa: str | None = None, saturation: float | None = None,
             **overrides) -> Estimate:
    """Estimate the gain map of a burst.

    Parameters
    ----------
    inputs : path, glob, directory, list of them, or ndarray
        Frame files (EXR or RAW), or the frames themselves as an array ``(F, H, W)`` or
        ``(F, H, W, C)`` in DN (offset removed), reference first.
    config, preset, overrides
        See :func:`config_of` (defaults < ``preset`` < ``config`` < ``overrides``).
    progress, executor
        The pipeline's progress hook, and a :class:`parallel.DaskExecutor` to solve on.
    cfa, saturation
        For an array: its 2x2 colour filter layout (``"RGGB"``; None for monochrome) and the
        level at which it clips.
    """
    cfg = config_of(config, preset=preset, **overrides)
    if isinstance(inputs, np.ndarray):
        if cfg.input.dark is not None:
            raise InputError("input.dark: subtract the dark frame from an array before passing it")
        saturation = cfg.input.saturation if saturation is None else saturation
        loaded = burst_of(inputs, cfa=cfa, saturation=saturation, reference=cfg.input.reference)
    else:
        loaded = load_burst([inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs), cfg,
                            progress=progress)
    result = _estimate(loaded, cfg, progress=progress, executor=executor)
    return Estimate(result.k, result.confidence, result.report, loaded, cfg, result.defects)


def burst_of(frames: np.ndarray, *, cfa: str | None = None, saturation: float | None = None,
             reference: int = 0) -> _burst.LoadedBurst:
    """A burst from frames in memory (named ``frame_000`` ... when written)."""
    frames = np.asarray(frames, np.float32)
    if frames.ndim == 3:
        frames = frames[..., None]
    if frames.ndim != 4 or frames.shape[3] not in (1, 3) or (cfa and frames.shape[3] != 1):
        raise InputError(f"frames must have shape (F, H, W) or (F, H, W, 3) (one channel for a CFA mosaic), "
                         f"got {frames.shape}")
    if not 0 <= reference < len(frames):
        raise InputError(f"input.reference is {reference} but there are only {len(frames)} frames")
    channels = ("Y",) if frames.shape[3] == 1 else ("R", "G", "B")[: frames.shape[3]]
    paths = [Path(f"frame_{i:03d}") for i in range(len(frames))]
    return _burst.LoadedBurst(paths, frames, cfa, channels, saturation, reference)


def apply(inputs, *, gain_map: str | os.PathLike, out_dir: str | os.PathLike, dark: str | os.PathLike | None = None,
          overwrite: bool = False, progress=None, repair: bool = True) -> list[Path]:
    """Correct other captures with a stored gain map, as ``estimate`` corrects its own frames
    (the map's dark frame subtracted first, with ``repair`` its defective photosites replaced
    from their neighbours); return the corrected frames written."""
    inputs = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
    written, _ = apply_gain_map(Path(gain_map), inputs, Path(out_dir), dark=None if dark is None else Path(dark),
                                overwrite=overwrite, progress=progress, repair=repair)
    return written
