"""Plain data handed between the stages: the loaded burst and its estimate."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .files import FileStamp

#: progress(stage, total) -> update(n): the CLI's tqdm, or nothing
Progress = Callable[[str, int], Callable[[int], None]]


@dataclass(frozen=True)
class LoadedBurst:
    paths: list[Path]
    frames: np.ndarray  # (F, H, W, C) float32, DN after black level (and dark frame)
    cfa: str | None
    channels: tuple[str, ...]
    saturation: float | None
    reference: int
    stamps: tuple[FileStamp, ...] = ()  # each frame file's path, size, time and digest
    dark: FileStamp | None = None  # the master dark frame subtracted, if any
    read_s: float = 0.0  # time taken to read the frames
    white: float | None = None  # the files' white level in DN (black level included), when they state one


@dataclass(frozen=True)
class Estimate:
    k: np.ndarray  # (H, W, C) float32
    confidence: np.ndarray  # (H, W, C) float32
    report: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
