"""Frames to arrays: EXR through OpenImageIO, RAW through rawpy (LibRaw).

Frames come back as float32 ``(H, W, C)`` arrays in DN with the black level already
subtracted (RAW) together with a :class:`FrameInfo` header. Library errors become
:class:`InputError` naming the file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from ..errors import InputError
from .frames import ATTR_CFA, ATTR_SATURATION, Frame, FrameInfo, kind_of


def read_frame(path: str | os.PathLike) -> Frame:
    """Read one EXR or RAW frame; raise :class:`InputError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: file is empty")
    try:
        frame = read_exr(path) if kind_of(path) == "exr" else read_raw(path)
    except UnicodeDecodeError:  # OpenImageIO passes a damaged header's bytes into its strings
        raise InputError(f"{path}: damaged header (names or messages that are not text)") from None
    check_finite(frame.data, path)
    return frame


def check_finite(data: np.ndarray, path: Path) -> None:
    if np.isfinite(data).all():
        return
    bad = ~np.isfinite(data)
    if bad.any():
        row, col, _ = np.argwhere(bad)[0]
        raise InputError(f"{path}: {int(bad.sum())} NaN/Inf pixel values (first at row {row}, column {col})")


def _pick_channels(names: Sequence[str]) -> list[int]:
    if "Y" in names:
        return [names.index("Y")]
    if all(c in names for c in "RGB"):
        return [names.index(c) for c in "RGB"]
    if len(names) == 1:
        return [0]
    return []


def read_oiio(path: Path, *, what: str, require_exr: bool) -> tuple[np.ndarray, object]:
    """Every channel of an image as float32 ``(H, W, C)`` and a copy of its spec.

    OpenImageIO never raises: each ``None`` / ``False`` is turned into an
    :class:`InputError` naming the file.
    """
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: not a readable {what} ({oiio_error(oiio.geterror())})")
    try:
        if require_exr and inp.format_name() != "openexr":
            raise InputError(f"{path}: not an OpenEXR file (it reads as {inp.format_name()})")
        spec = oiio.ImageSpec(inp.spec())
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise InputError(f"{path}: cannot read pixels, file damaged or truncated ({oiio_error(inp.geterror())})")
    finally:
        inp.close()
    return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels), spec


def read_exr(path: Path) -> Frame:
    """Read a single-channel (``Y``, or any one channel) or RGB EXR as float32."""
    pixels, spec = read_oiio(path, what="EXR file", require_exr=True)
    names = list(spec.channelnames)
    picked = _pick_channels(names)
    if not picked:
        raise InputError(f"{path}: no usable channel (want Y, or R G B, or a single channel; has {', '.join(names)})")
    cfa = spec.get_string_attribute(ATTR_CFA) or None
    saturation = spec.getattribute(ATTR_SATURATION)
    info = FrameInfo(
        path=path,
        kind="exr",
        shape=(spec.height, spec.width),
        channels=tuple(names[i] for i in picked),
        cfa=cfa,
        saturation=None if saturation is None else float(saturation),
        source_type=str(spec.format),
    )
    if info.cfa is not None:
        _check_cfa(info.cfa, path)
        if len(picked) != 1:
            raise InputError(f"{path}: a CFA mosaic ({info.cfa}) must have one channel, has {len(picked)}")
    every = picked == list(range(pixels.shape[2]))  # a fancy index copies the frame
    return Frame(pixels if every else np.ascontiguousarray(pixels[:, :, picked]), info)


def oiio_error(message: str) -> str:
    return message.strip().splitlines()[-1] if message and message.strip() else "unknown error"


def _check_cfa(cfa: str, path: Path) -> None:
    if len(cfa) != 4 or set(cfa) - set("RGBCMYW"):
        raise InputError(f"{path}: CFA layout {cfa!r} is not a 2x2 pattern such as RGGB")


def read_raw(path: Path) -> Frame:
    """Read the visible mosaic of any file LibRaw reads, black level subtracted.

    The black level per photosite is ``black_level_per_channel`` indexed by the
    photosite's colour index (not by its position in the 2x2 cell).
    """
    import rawpy

    try:
        with _captured_stderr() as said, rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible.copy()
            colors = raw.raw_colors_visible.copy()
            pattern = None if raw.raw_pattern is None else np.array(raw.raw_pattern)
            desc = raw.color_desc.decode("ascii", "replace")
            black_per_color = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = float(raw.white_level)
    except rawpy.LibRawError as exc:
        detail = f"; LibRaw: {said[0]}" if said and said[0] else ""
        raise InputError(f"{path}: not a RAW file LibRaw can read ({_libraw_reason(exc)}{detail})") from None
    if mosaic.ndim != 2:
        raise InputError(f"{path}: RAW data is not a single-plane mosaic (shape {mosaic.shape})")
    if pattern is None or pattern.shape != (2, 2):
        shape = None if pattern is None else pattern.shape
        raise InputError(f"{path}: only 2x2 colour filter arrays are supported (this file has {shape})")
    cfa = "".join(desc[c] for c in pattern.ravel())
    black_map = black_per_color[colors]
    data = mosaic.astype(np.float32) - black_map
    black = tuple(float(black_per_color[c]) for c in pattern.ravel())
    info = FrameInfo(
        path=path,
        kind="raw",
        shape=mosaic.shape,
        channels=("raw",),
        cfa=cfa,
        saturation=white - max(black),
        black=black,
        source_type=str(mosaic.dtype),
    )
    return Frame(data[:, :, None], info)


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Capture what C code writes to file descriptor 2 (LibRaw prints there).

    Yields a list that holds the captured text, last line only, once the
    block ends, so a user sees one error line instead of LibRaw's own.
    """
    said: list[str] = []
    with tempfile.TemporaryFile(mode="w+b") as sink:
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace").strip()
            said.append(text.splitlines()[-1].split(": ", 1)[-1] if text else "")


def _libraw_reason(exc: Exception) -> str:
    name = type(exc).__name__
    reasons = {
        "LibRawFileUnsupportedError": "unsupported or not a RAW file",
        "LibRawIOError": "I/O error, file damaged or truncated",
        "LibRawDataError": "data error, file damaged or truncated",
        "LibRawTooBigError": "image too big or damaged",
        "LibRawRequestForNonexistentImageError": "no image in the file",
    }
    return reasons.get(name, f"{name}: {exc}" if str(exc) else name)


def read_stack(paths: Sequence[Path]) -> list[Frame]:
    """Read frames and check they share kind, size, channels and CFA layout."""
    frames = [read_frame(p) for p in paths]
    check_consistent([f.info for f in frames])
    return frames


def check_consistent(infos: Sequence[FrameInfo]) -> None:
    """Raise :class:`InputError` naming the first frame that differs from the first."""
    if not infos:
        raise InputError("no input frames given")
    first = infos[0]
    labels = ("file type", "size", "channels", "CFA layout", "white level")
    for info in infos[1:]:
        for label, a, b in zip(labels, first.layout(), info.layout()):
            if a != b:
                raise InputError(f"{info.path}: {label} {_fmt(b)} differs from {first.path.name} ({_fmt(a)})")


def _fmt(value) -> str:
    if value is None:
        return "not stated"
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return f"{value[1]}x{value[0]}"
    if isinstance(value, tuple):
        return ",".join(value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def read_exr_planes(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every channel of an EXR by name (float32 ``(H, W)``) and its gainfpn attributes."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    pixels, spec = read_oiio(path, what="EXR file", require_exr=True)
    planes = {name: pixels[:, :, i].copy() for i, name in enumerate(spec.channelnames)}
    attrs = {a.name: str(a.value) for a in spec.extra_attribs if a.name.startswith("gainfpn:")}
    return planes, attrs
