"""Plain data handed between the stages: the loaded burst and its estimate."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .files import FileStamp
from .report import Report

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
    dark_hot: np.ndarray | None = None  # (H, W, C) bool: the hot photosites the dark frame shows


@dataclass(frozen=True)
class Estimate:
    """A gain map and its report: ``k`` and ``confidence`` ``(H, W, C)`` float32, and the
    defective photosites ``(H, W, C)`` uint8 (:data:`solve.defects.KINDS`; None: not searched)."""

    k: np.ndarray
    confidence: np.ndarray
    report: Report
    defects: np.ndarray | None = None

    @property
    def warnings(self) -> tuple[str, ...]:
        return self.report.warnings
