"""Arrays to files, atomically: a temporary name beside the final one, renamed into place only
when complete, so a failed or interrupted write leaves no half-written file under a final name."""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from ..errors import InputError
from .read import oiio_error


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success.

    On any exception (KeyboardInterrupt included) the temporary file is removed
    and ``path`` is left as it was. The temporary name keeps the suffix, so
    writers that pick a format from it still do.
    """
    path = Path(path)
    tmp = _new_file(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _new_file(path: Path) -> Path:
    """Create an empty, uniquely named file beside ``path`` (its suffix kept, for writers that
    pick a format from it), with the permissions the umask gives: no umask is read or changed."""
    for _ in range(100):
        tmp = path.parent / f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
        except OSError as exc:
            raise InputError(f"{path}: cannot write here ({exc.strerror or exc})") from None
    raise InputError(f"{path}: cannot write here (no free temporary name)")


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
            raise InputError(f"{path}: cannot create EXR writer ({oiio_error(oiio.geterror())})")
        ok = out.open(str(tmp), spec) and out.write_image(pixels)
        error = "" if ok else out.geterror()
        ok = out.close() and ok
        if not ok:
            raise InputError(f"{path}: cannot write EXR ({oiio_error(error or out.geterror())})")
