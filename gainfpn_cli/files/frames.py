"""What an input is: frame files found from paths, directories and globs; a frame's header;
which file it was (path, size, time, digest)."""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError

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
