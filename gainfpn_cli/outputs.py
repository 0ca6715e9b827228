"""An estimate's folder: the gain map, the corrected frames, the preview, the report; and
``apply``, which corrects other captures from a stored map exactly as ``estimate`` does.

Every folder is written through :mod:`outdir`: staged, then moved in by name.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import __version__
from .burst import Estimate, LoadedBurst, Progress
from .config import Config, dump_config
from .defective import repair
from .errors import EstimationError, InputError
from .files import (
    ATTR_CFA,
    ATTR_SATURATION,
    check_consistent,
    find_frames,
    read_exr_planes,
    read_frame,
    stamp,
    write_exr,
    write_text,
)
from .outdir import OutputPlan, prepare, staged
from .preview import write_preview
from .report import Report
from .solve.defects import KINDS


def _gain_planes(k: np.ndarray, confidence: np.ndarray, defects: np.ndarray | None, channels: tuple[str, ...],
                 cfa: str | None) -> dict:
    """The channels of gain_map.exr: k, its confidence and (when looked for) the defect codes,
    for one plane (``Y``, ``confidence``, ``defect``) or per colour (``R``, ``R.confidence``, ...)."""
    names = ("Y",) if cfa or len(channels) == 1 else channels
    planes = {}
    for c, name in enumerate(names):
        prefix = "" if name == "Y" else f"{name}."
        planes[name] = k[..., c]
        planes[f"{prefix}confidence"] = confidence[..., c]
        if defects is not None:
            planes[f"{prefix}defect"] = defects[..., c].astype(np.float32)
    return planes


@dataclass(frozen=True)
class Written:
    """An estimate's folder once written: its output plan and the report as written."""

    plan: OutputPlan
    report: Report


#: Header attribute of a gain map estimated on dark-subtracted frames: that dark frame's path and digest.
ATTR_DARK = "gainfpn:dark"


#: What ``estimate`` writes into its output folder (``--overwrite`` replaces these names only).
ESTIMATE_OUTPUTS = ("gain_map.exr", "corrected", "preview.png", "config.used.yaml", "report.json")


def estimate_plan(out_dir: Path, paths, cfg: Config, *, overwrite: bool = False, files=None,
                  also_read=()) -> OutputPlan:
    """Check ``out_dir`` for an estimate of the frames ``paths`` before any work (:func:`outdir.prepare`);
    ``files`` are the frames' files if not ``paths`` (none for frames given as an array), ``also_read``
    other files the run reads (its config)."""
    _check_unique_stems(list(paths))
    inputs = [*(paths if files is None else files), *([cfg.input.dark] if cfg.input.dark else []), *also_read]
    skipped = {"corrected"} if not cfg.output.corrected else set()
    skipped |= {"preview.png"} if not cfg.output.preview else set()
    return prepare(out_dir, command="estimate", names=[n for n in ESTIMATE_OUTPUTS if n not in skipped],
                   inputs=inputs, overwrite=overwrite)


def write_estimate(result: Estimate, burst: LoadedBurst, cfg: Config, out_dir: Path, *, overwrite: bool = False,
                   progress: Progress | None = None) -> Written:
    """gain_map.exr, corrected/*.exr, report.json, config.used.yaml and preview.png, all or nothing.

    Only these names are replaced in ``out_dir`` (and an earlier evaluation of them removed).
    Returns the output plan (what else the folder holds, untouched) and the report as written
    (with the write and total times)."""
    plan = estimate_plan(out_dir, burst.paths, cfg, overwrite=overwrite, files=[s.path for s in burst.stamps])
    t0 = time.perf_counter()
    config_text = dump_config(cfg)
    metadata = {"gainfpn:version": __version__, "gainfpn:config": config_text,
                "gainfpn:inputs": json.dumps([str(p.absolute()) for p in burst.paths]),
                "gainfpn:motion_model": result.report.motion.model}
    if burst.dark is not None:  # `apply` subtracts the same dark frame before k
        metadata[ATTR_DARK] = json.dumps({"path": burst.dark.path, "sha256": burst.dark.sha256})
    if burst.cfa:
        metadata[ATTR_CFA] = burst.cfa
    with staged(plan) as tmp:
        write_exr(tmp / "gain_map.exr", _gain_planes(result.k, result.confidence, result.defects, burst.channels,
                                                     burst.cfa), metadata=metadata, compression=cfg.output.compression)
        if cfg.output.corrected:
            (tmp / "corrected").mkdir()
            update = progress("write", len(burst.paths)) if progress else None
            repair = result.defects if cfg.output.repair else None
            _write_corrected(lambda i: (burst.paths[i], burst.frames[i]), len(burst.paths), result.k,
                             tmp / "corrected", cfa=burst.cfa, channels=burst.channels, saturation=burst.saturation,
                             compression=cfg.output.compression, update=update, defects=repair)
        if cfg.output.preview:
            write_preview(tmp / "preview.png", result.k, result.confidence, report=result.report,
                          name=burst_name(burst.paths), cfa=burst.cfa, channels=burst.channels)
        write_text(tmp / "config.used.yaml", config_text)
        report = result.report.with_timings(write_s=time.perf_counter() - t0)
        write_text(tmp / "report.json", json.dumps(report.to_json(), indent=1))
    return Written(plan, report)


def _write_corrected(frame: Callable[[int], tuple[Path, np.ndarray]], count: int, k: np.ndarray, folder: Path, *,
                     cfa: str | None, channels: tuple[str, ...], saturation: float | None, compression: str,
                     update=None, defects: np.ndarray | None = None) -> None:
    """``folder/<stem>.exr`` = ``k`` times each frame ``frame(i) -> (path, DN)`` for ``i < count``,
    its ``defects`` (if given) repaired from their neighbours: the one writer of corrected frames,
    for ``estimate`` and ``apply`` alike."""
    names = ("Y",) if cfa or len(channels) == 1 else channels
    metadata: dict = {"gainfpn:version": __version__}
    if cfa:
        metadata[ATTR_CFA] = cfa
    if saturation is not None:
        metadata[ATTR_SATURATION] = float(saturation)

    def write(i: int) -> None:
        path, data = frame(i)
        corrected = data * k
        if defects is not None:
            corrected = repair(corrected, defects, cfa, channels)
        _check_finite(corrected, path)
        write_exr(folder / f"{path.stem}.exr", {n: corrected[..., c] for c, n in enumerate(names)},
                  metadata=metadata, compression=compression)

    for i in range(0, count, 2):
        _in_pair(write, i, i + 1 < count)
        if update:
            update(min(2, count - i))


def burst_name(paths: list[Path]) -> str:
    """What the preview's title calls a burst: its folder, or its first and last frames."""
    folders = {p.absolute().parent for p in paths}
    if len(folders) == 1:
        return f"{folders.pop().name}/"
    return f"{paths[0].name} ... {paths[-1].name}"


def _check_unique_stems(paths: list[Path]) -> None:
    """Corrected frames are named by their input's stem: two inputs must not share one."""
    seen: dict[str, Path] = {}
    for path in paths:
        if path.stem in seen:
            raise InputError(f"{path}: has the same name as {seen[path.stem]}; their corrected frames would both "
                             f"be {path.stem}.exr")
        seen[path.stem] = path


#: On an error or an interrupt, how long (s) the other frame's write may take to finish (a 12 MP
#: frame takes ~0.1 s) before the staging directory is removed under it.
WRITE_GRACE_S = 5.0


def _in_pair(fn: Callable[[int], None], i: int, both: bool) -> None:
    """``fn(i)`` here and, if ``both``, ``fn(i + 1)`` at the same time on a daemon thread.

    OpenImageIO releases the GIL while it encodes and writes, so two frames at
    a time take half the time (12 MP x 8 uncompressed: 0.94 -> 0.49 s). The
    thread is a daemon: an interrupt here waits for it at most WRITE_GRACE_S
    (then the staging directory it writes into is removed).
    """
    failed: list[BaseException] = []

    def other() -> None:
        try:
            fn(i + 1)
        except BaseException as exc:  # raised here, in the caller's thread
            failed.append(exc)

    thread = threading.Thread(target=other, daemon=True) if both else None
    if thread:
        thread.start()
    try:
        fn(i)
    except BaseException:  # give the other write a moment to finish before its folder is removed
        if thread:
            thread.join(timeout=WRITE_GRACE_S)
        raise
    if thread:
        thread.join()
    if failed:
        raise failed[0]


def _check_finite(corrected: np.ndarray, path: Path) -> None:
    if not np.isfinite(corrected).all():
        raise EstimationError(f"{path}: the corrected frame exceeds the float32 range (inputs near 3.4e38); "
                              "scale the input down")


# ---------------------------------------------------------------------------
# apply and evaluate


def read_gain_map(path: Path) -> tuple[np.ndarray, dict]:
    """k as ``(H, W, C)`` and the map's attributes."""
    k, attrs, _ = read_gain_map_defects(path)
    return k, attrs


def read_gain_map_defects(path: Path) -> tuple[np.ndarray, dict, np.ndarray | None]:
    """k as ``(H, W, C)``, the map's attributes and its defect codes ``(H, W, C)`` uint8 (None
    for a map written without them)."""
    planes, attrs = read_exr_planes(path)
    names = ["Y"] if "Y" in planes else [n for n in ("R", "G", "B") if n in planes]
    if not names:
        raise InputError(f"{path}: not a gainfpn gain map (no Y or R G B channel)")
    k = np.stack([planes[n] for n in names], axis=-1)
    defect = ["defect" if n == "Y" else f"{n}.defect" for n in names]
    if not all(d in planes for d in defect):
        return k, attrs, None
    codes = np.stack([planes[d] for d in defect], axis=-1)
    if not np.isin(codes, [0, *KINDS.values()]).all():
        raise InputError(f"{path}: damaged defect channel (codes other than 0 and {sorted(KINDS.values())})")
    return k, attrs, codes.astype(np.uint8)


def apply_dark(attrs: dict, dark: Path | None, gain_map: Path) -> Path | None:
    """The dark frame to subtract before ``k``: the one the map was estimated with (its header
    records path and digest), found at its recorded path or given as ``dark``; a different
    dark frame, or one for a map estimated without, is refused."""
    try:
        recorded = json.loads(attrs[ATTR_DARK]) if ATTR_DARK in attrs else None
        recorded = None if recorded is None else {"path": str(recorded["path"]), "sha256": str(recorded["sha256"])}
    except (ValueError, KeyError, TypeError):
        raise InputError(f"{gain_map}: damaged header (its {ATTR_DARK} attribute is not a path and a digest)") from None
    if recorded is None:
        if dark is not None:
            raise InputError(f"{gain_map}: was estimated without a dark frame, so --dark {dark} would correct "
                             "differently from the estimate; subtract it from the inputs first, or estimate with it")
        return None
    if dark is None:
        dark = Path(recorded["path"])
        if not dark.is_file():
            raise InputError(f"{gain_map}: was estimated with the dark frame {recorded['path']} subtracted, which is "
                             "gone; pass it with --dark")
    if stamp(dark).sha256 != recorded["sha256"]:
        raise InputError(f"{dark}: is not the dark frame the gain map was estimated with ({recorded['path']}, "
                         f"sha256 {recorded['sha256'][:12]}...)")
    return dark


def apply_plan(gain_map: Path, paths: list[Path], out_dir: Path, *, dark: Path | None = None,
               overwrite: bool = False) -> OutputPlan:
    """Check ``out_dir`` for the corrected frames of ``paths`` before any work (:func:`outdir.prepare`)."""
    _check_unique_stems(paths)
    return prepare(out_dir, command="apply", names=[f"{p.stem}.exr" for p in paths],
                   inputs=[*paths, gain_map, *([dark] if dark else [])], overwrite=overwrite)


def apply_gain_map(gain_map: Path, inputs, out_dir: Path, *, dark: Path | None = None, overwrite: bool = False,
                   progress: Progress | None = None, repair: bool = True) -> tuple[list[Path], OutputPlan]:
    """Correct other captures with a stored map, exactly as ``estimate`` corrects its own frames
    (the map's dark frame subtracted first, with ``repair`` the map's defective photosites
    replaced from their neighbours); return the frames written and the output plan."""
    k, attrs, defects = read_gain_map_defects(gain_map)
    dark = apply_dark(attrs, dark, gain_map)
    paths = find_frames(inputs)
    plan = apply_plan(gain_map, paths, out_dir, dark=dark, overwrite=overwrite)
    dark_data = None if dark is None else read_frame(dark).data
    if dark_data is not None and dark_data.shape != k.shape:
        raise InputError(f"{dark}: dark frame is {dark_data.shape[1]}x{dark_data.shape[0]}, the gain map "
                         f"{k.shape[1]}x{k.shape[0]}")
    update = progress("apply", len(paths)) if progress else None
    first = read_frame(paths[0])

    def frame(i: int) -> tuple[Path, np.ndarray]:
        read = first if i == 0 else read_frame(paths[i])
        check_consistent([first.info, read.info])
        data = read.data
        if data.shape != k.shape:
            raise InputError(f"{read.info.path}: frame is {data.shape[1]}x{data.shape[0]} with {data.shape[2]} "
                             f"channel(s); the gain map is {k.shape[1]}x{k.shape[0]} with {k.shape[2]}")
        if (read.info.cfa or None) != (attrs.get(ATTR_CFA) or None):
            raise InputError(f"{read.info.path}: CFA layout {read.info.cfa or 'none'} does not match the gain map's "
                             f"{attrs.get(ATTR_CFA) or 'none'}")
        return read.info.path, data if dark_data is None else data - dark_data

    with staged(plan) as tmp:
        _write_corrected(frame, len(paths), k, tmp, cfa=first.info.cfa, channels=first.info.channels,
                         saturation=first.info.saturation, compression="zip", update=update,
                         defects=defects if repair else None)
    return [out_dir / f"{p.stem}.exr" for p in paths], plan
