"""Files to arrays and back: EXR through OpenImageIO, RAW through rawpy (LibRaw).

This is the only module that touches image files. Library errors are turned
into :class:`InputError` naming the file; every write is atomic (temporary
name in the same directory, then rename), so a failed or interrupted run
leaves no half-written file under a final name.

Frames come back as float32 ``(H, W, C)`` arrays in DN with the black level
already subtracted (RAW) together with a :class:`FrameInfo` header.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np

from .errors import InputError

EXR_SUFFIXES = frozenset({".exr"})
#: Extensions picked up from a directory as RAW; an explicitly named file of
#: any other extension is still tried with LibRaw.
RAW_SUFFIXES = frozenset(
    ".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .orf .rw2 .raf .pef .srw "
    ".3fr .iiq .erf .mos .mrw .kdc .dcr .x3f .rwl .raw".split()
)

FRAME_SUFFIXES = EXR_SUFFIXES | RAW_SUFFIXES

#: EXR header attributes written by gainfpn (and read back from its own files).
ATTR_CFA = "gainfpn:cfa"
ATTR_SATURATION = "gainfpn:saturation"

_UMASK = os.umask(0o022)
os.umask(_UMASK)


@dataclass(frozen=True)
class FrameInfo:
    """What a frame is, without its pixels.

    Attributes
    ----------
    path : Path
    kind : {"exr", "raw"}
    shape : (int, int)
        ``(H, W)`` in pixels (photosites for RAW).
    channels : tuple of str
        Channel names of the returned array's last axis (``("raw",)`` for RAW).
    cfa : str or None
        2x2 colour filter layout in row-major order (``"RGGB"``), or None for
        a monochrome or already demosaiced frame.
    saturation : float or None
        Level in DN (after black-level subtraction) at or above which a pixel
        is clipped, when the file states one.
    black : tuple of float
        Black level per 2x2 CFA position (row-major) that was subtracted;
        empty for EXR.
    source_type : str
        Pixel type in the file (``"half"``, ``"float"``, ``"uint16"``).
    """

    path: Path
    kind: str
    shape: tuple[int, int]
    channels: tuple[str, ...]
    cfa: str | None = None
    saturation: float | None = None
    black: tuple[float, ...] = ()
    source_type: str = "float"

    def layout(self) -> tuple:
        """The properties every frame of one burst must share (the white level, not the
        saturation above black: a black level may drift from frame to frame)."""
        white = None if self.saturation is None else self.saturation + max(self.black, default=0.0)
        return (self.kind, self.shape, self.channels, self.cfa, white)


@dataclass(frozen=True)
class Frame:
    """A frame's pixels (float32 ``(H, W, C)``, DN after black level) and header."""

    data: np.ndarray = field(repr=False)
    info: FrameInfo


@dataclass(frozen=True)
class FileStamp:
    """Which file an input was: absolute path, size, modification time and content digest.

    ``batch`` compares path, size and time to tell whether a stored result is still the
    inputs'; ``evaluate`` compares the digest with the simulation's frames.
    """

    path: str
    size_bytes: int
    mtime_ns: int
    sha256: str

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def same_file(self, other: "FileStamp") -> bool:
        """Same path, size and modification time (the digest is not read)."""
        return (self.path, self.size_bytes, self.mtime_ns) == (other.path, other.size_bytes, other.mtime_ns)


def stamp(path: str | os.PathLike, *, digest: bool = True) -> FileStamp:
    """The :class:`FileStamp` of ``path`` (``sha256`` empty without ``digest``: 1.5 GB/s measured)."""
    path = Path(path).absolute()
    try:
        st = path.stat()
        sha = ""
        if digest:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            sha = h.hexdigest()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return FileStamp(str(path), st.st_size, st.st_mtime_ns, sha)


# ---------------------------------------------------------------------------
# finding inputs


def kind_of(path: Path) -> str:
    """``"exr"`` for ``.exr`` files, ``"raw"`` for anything else."""
    return "exr" if path.suffix.lower() in EXR_SUFFIXES else "raw"


def find_frames(specs: Sequence[str | os.PathLike]) -> list[Path]:
    """Expand files, directories and glob patterns into a sorted list of frames.

    A directory or a glob pattern contributes its EXR and RAW files (by
    extension, not recursively; other files are skipped); a file named
    explicitly is read whatever its extension. Frames are sorted by name; duplicates are dropped.
    """
    if not specs:
        raise InputError("no input frames given")
    found: set[Path] = set()
    for spec in specs:
        text = os.fspath(spec)
        path = Path(text)
        if path.is_dir():
            members = [p for p in path.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES]
            if not members:
                raise InputError(f"{path}: directory holds no EXR or RAW frames")
            found.update(members)
        elif path.exists():
            if not path.is_file():
                raise InputError(f"{path}: not a regular file")
            found.add(path)
        elif glob.has_magic(text):  # as a directory: frames by extension, other files skipped
            matches = [Path(m) for m in glob.glob(text) if Path(m).is_file()]
            if not matches:
                raise InputError(f"{text}: pattern matches no file")
            frames = [p for p in matches if p.suffix.lower() in FRAME_SUFFIXES]
            if not frames:
                raise InputError(f"{text}: pattern matches no EXR or RAW frame (only {_some(matches)})")
            found.update(frames)
        else:
            raise InputError(f"{path}: no such file or directory")
    return sorted(found, key=lambda p: (p.name, str(p)))


def _some(paths: Sequence[Path]) -> str:
    names = sorted(p.name for p in paths)
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


# ---------------------------------------------------------------------------
# reading


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
    _check_finite(frame.data, path)
    return frame


def _check_finite(data: np.ndarray, path: Path) -> None:
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


def _read_oiio(path: Path, *, what: str, require_exr: bool) -> tuple[np.ndarray, object]:
    """Every channel of an image as float32 ``(H, W, C)`` and a copy of its spec.

    OpenImageIO never raises: each ``None`` / ``False`` is turned into an
    :class:`InputError` naming the file.
    """
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: not a readable {what} ({_oiio_error(oiio.geterror())})")
    try:
        if require_exr and inp.format_name() != "openexr":
            raise InputError(f"{path}: not an OpenEXR file (it reads as {inp.format_name()})")
        spec = oiio.ImageSpec(inp.spec())
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise InputError(f"{path}: cannot read pixels, file damaged or truncated ({_oiio_error(inp.geterror())})")
    finally:
        inp.close()
    return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels), spec


def read_exr(path: Path) -> Frame:
    """Read a single-channel (``Y``, or any one channel) or RGB EXR as float32."""
    pixels, spec = _read_oiio(path, what="EXR file", require_exr=True)
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


def _oiio_error(message: str) -> str:
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
    pixels, spec = _read_oiio(path, what="EXR file", require_exr=True)
    planes = {name: pixels[:, :, i].copy() for i, name in enumerate(spec.channelnames)}
    attrs = {a.name: str(a.value) for a in spec.extra_attribs if a.name.startswith("gainfpn:")}
    return planes, attrs


# ---------------------------------------------------------------------------
# writing


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    On any exception (KeyboardInterrupt included) the temporary file is removed
    and ``path`` is left as it was. The temporary name keeps the suffix, so
    writers that pick a format from it still do.
    """
    path = Path(path)
    try:
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    except OSError as exc:
        raise InputError(f"{path}: cannot write here ({exc.strerror or exc})") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs follow the umask
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write a text file atomically."""
    with atomic_output(path) as tmp:
        try:
            tmp.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise InputError(f"{path}: cannot write ({exc.strerror or exc})") from None


def write_exr(
    path: str | os.PathLike,
    planes: Mapping[str, np.ndarray],
    *,
    metadata: Mapping[str, str | int | float] | None = None,
    compression: str = "zip",
) -> None:
    """Write named float32 ``(H, W)`` planes to an EXR atomically.

    ``metadata`` values become header attributes; keep exact numbers in
    strings (OpenImageIO stores Python floats as float32).
    """
    import OpenImageIO as oiio

    if not planes:
        raise ValueError("planes must hold at least one channel")
    arrays = [np.asarray(p, dtype=np.float32) for p in planes.values()]
    shape = arrays[0].shape
    if len(shape) != 2 or any(a.shape != shape for a in arrays):
        raise ValueError(f"planes must be 2-D and of one shape, got {[a.shape for a in arrays]}")
    pixels = np.ascontiguousarray(np.stack(arrays, axis=-1))  # (H, W, C): OIIO misreads 2-D arrays
    spec = oiio.ImageSpec(shape[1], shape[0], len(arrays), "float")
    spec.channelnames = tuple(planes)
    spec.attribute("compression", compression)
    for key, value in (metadata or {}).items():
        spec.attribute(key, value)
    path = Path(path)
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise InputError(f"{path}: cannot create EXR writer ({_oiio_error(oiio.geterror())})")
        ok = out.open(str(tmp), spec) and out.write_image(pixels)
        error = "" if ok else out.geterror()
        ok = out.close() and ok
        if not ok:
            raise InputError(f"{path}: cannot write EXR ({_oiio_error(error or out.geterror())})")


def write_dng(
    path: str | os.PathLike,
    mosaic: np.ndarray,
    *,
    bits: int,
    cfa: str,
    black: Sequence[int],
    white: int,
) -> None:
    """Write an uncompressed CFA DNG (pidng) that rawpy reads back exactly.

    Parameters
    ----------
    mosaic : ndarray of uint16, shape (H, W)
        Raw counts, black level included.
    bits : {8, 10, 12, 16}
        Stored bit depth (14-bit data go in a 16-bit container: pidng's 14-bit
        packing is wrong).
    cfa : str
        2x2 layout, e.g. ``"RGGB"``.
    black : sequence of 4 int
        Black level per 2x2 position, row-major.
    """
    try:
        from pidng.core import RAW2DNG, DNGTags, Tag
        from pidng.defs import CalibrationIlluminant, DNGVersion, PhotometricInterpretation
    except ImportError:
        raise InputError("writing DNG needs pidng: pip install 'gainfpn[dng]'") from None
    mosaic = np.asarray(mosaic)
    height, width = mosaic.shape
    if bits not in (8, 10, 12, 16):
        raise ValueError(f"bits must be 8, 10, 12 or 16, got {bits}")
    if (bits == 10 and width % 4) or (bits == 12 and width % 2):
        raise ValueError(f"{bits}-bit DNG needs a width divisible by {4 if bits == 10 else 2}, got {width}")
    if mosaic.dtype != np.uint16 or int(mosaic.max(initial=0)) >= 2**bits:
        raise ValueError(f"mosaic must be uint16 below 2**{bits}")
    codes = {"R": 0, "G": 1, "B": 2}
    tags = DNGTags()
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.TileWidth, width)
    tags.set(Tag.TileLength, height)
    tags.set(Tag.Orientation, 1)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, bits)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, [codes[c] for c in cfa])
    tags.set(Tag.BlackLevelRepeatDim, [2, 2])
    tags.set(Tag.BlackLevel, [int(b) for b in black])
    tags.set(Tag.WhiteLevel, int(white))
    tags.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    tags.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    tags.set(Tag.Make, "gainfpn")
    tags.set(Tag.Model, "simulator")
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    data = bytes(writer.convert(mosaic))
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


def read_scene(path: str | os.PathLike) -> np.ndarray:
    """Any image OpenImageIO reads, as a linear float32 scene in [0, 1].

    Integer files (PNG, JPEG, TIFF) are taken as sRGB-like and linearised
    with a 2.2 power; float files are used as they are, clipped to [0, 1].
    Returns ``(h, w)`` or ``(h, w, C)``.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    image, spec = _read_oiio(path, what="image", require_exr=False)
    is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    _check_finite(image, path)
    image = np.clip(image, 0.0, 1.0)
    if not is_float:
        image = image**2.2
    return image[:, :, 0] if image.shape[2] == 1 else image
