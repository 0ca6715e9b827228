"""Output folders that gainfpn owns by name: never delete what it did not write.

Every command writes its outputs into a staging folder beside OUT and, once
all of them are complete, moves them into OUT one name at a time. OUT keeps a
small manifest (:data:`MANIFEST`) of the names gainfpn wrote there and which
command wrote each, so that ``--overwrite`` replaces exactly:

* the names this run writes, and
* the names an earlier run of the same command wrote (an 8-frame simulation
  replaced by a 5-frame one leaves no stale ``frame_007``), together with the
  names of the commands whose results depend on them (a new estimate removes
  the ``evaluation.json`` of the old one).

Everything else in OUT (a user's notes, another tool's files) is left as it
is and reported. Before any work, :func:`prepare` refuses an OUT that is an
input, holds one (at any depth), or whose replacement would touch one.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from .errors import InputError

#: The manifest of what gainfpn wrote in a folder (JSON: ``{"entries": {name: command}}``).
MANIFEST = ".gainfpn-outputs.json"
#: Whose results go stale when a command writes again into the same folder.
DEPENDENTS = {"estimate": ("evaluate",)}


@dataclass(frozen=True)
class OutputPlan:
    """What a command may do in its output folder, settled before any work.

    Attributes
    ----------
    out_dir : Path
    command : str
        The command writing (``"estimate"``, ``"apply"``, ...), recorded in the manifest.
    replace : frozenset of str
        Names in ``out_dir`` that the commit removes or replaces (earlier outputs of
        this command and of its dependents, and the names this run writes).
    untouched : tuple of str
        Names in ``out_dir`` that gainfpn did not write: never touched.
    """

    out_dir: Path
    command: str
    replace: frozenset
    untouched: tuple


def read_manifest(out_dir: Path) -> dict[str, str]:
    """``{name: command}`` of what gainfpn wrote in ``out_dir`` (empty without a readable manifest)."""
    try:
        data = json.loads((Path(out_dir) / MANIFEST).read_text(encoding="utf-8"))
        entries = data["entries"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    if not isinstance(entries, dict):
        return {}
    # plain names only: a manifest edited to say "../x" must not reach outside the folder
    return {n: c for n, c in entries.items() if isinstance(n, str) and isinstance(c, str) and _plain_name(n)}


def _plain_name(name: str) -> bool:
    return bool(name) and name not in (".", "..", MANIFEST) and "/" not in name and os.sep not in name


def _real(path: str | os.PathLike) -> Path:
    return Path(os.path.realpath(path))


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def prepare(out_dir: str | os.PathLike, *, command: str, names: Iterable[str] = (), inputs: Iterable = (),
            overwrite: bool = False, beside_inputs: bool = False) -> OutputPlan:
    """Check ``out_dir`` before any work and settle what the commit may replace.

    Parameters
    ----------
    names : iterable of str
        The names this run writes into ``out_dir`` (as far as known before the work).
    inputs : iterable of path
        Every file the command reads (frames, dark frame, gain map, config, scene image).
    beside_inputs : bool
        Allow ``out_dir`` to hold inputs (``evaluate`` writes its one file into the
        estimate's folder); an input is still never among the names replaced.

    Raises
    ------
    InputError
        ``out_dir`` is or holds an input, is not a folder, cannot be made, or holds
        earlier results and ``overwrite`` is false.
    """
    out_dir = Path(out_dir)
    real_out = _real(out_dir)
    names = set(names)
    manifest = read_manifest(out_dir) if out_dir.is_dir() else {}
    stale = {n for n, c in manifest.items() if c == command or c in DEPENDENTS.get(command, ())}
    replace = {n for n in names | stale if _exists(out_dir / n)}
    foreign = sorted(n for n in replace if n not in manifest)
    if foreign:  # a name this run writes, held by something gainfpn did not write: never replaced
        raise InputError(f"{out_dir / foreign[0]}: exists and was not written by gainfpn (gainfpn would write "
                         "its own there); move it away or choose another output folder")
    for path in inputs:
        real = _real(path)
        if real == real_out:
            raise InputError(f"{out_dir}: is an input ({path}); choose another output folder")
        if _inside(real, real_out) and not beside_inputs:
            raise InputError(f"{out_dir}: holds the input {path}; choose an output folder outside the inputs")
        hit = next((n for n in replace if _inside(real, _real(out_dir / n))), None)
        if hit is not None:
            raise InputError(f"{out_dir / hit}: would be replaced but holds the input {path}; choose another output "
                             "folder")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a directory")
    parent = out_dir.absolute().parent  # created when the results are written, as mkdir -p would
    existing = next(p for p in (parent, *parent.parents) if p.exists())
    if not existing.is_dir():
        raise InputError(f"{existing}: is not a directory, so {out_dir} cannot be made")
    if replace and not overwrite:
        shown = ", ".join(sorted(replace)[:3]) + (", ..." if len(replace) > 3 else "")
        raise InputError(f"{out_dir}: already holds results of gainfpn ({shown}); pass --overwrite to replace them "
                         "(files gainfpn did not write are left alone)")
    untouched = ()
    if out_dir.is_dir():
        untouched = tuple(sorted(p.name for p in out_dir.iterdir()
                                 if p.name != MANIFEST and p.name not in manifest and p.name not in names))
    return OutputPlan(out_dir, command, frozenset(replace), untouched)


def _exists(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def _beside(out_dir: Path, kind: str, pid: str) -> Path:
    """A folder beside ``out_dir`` (beside what a link named ``out_dir`` points to: on its file
    system, so that every move into ``out_dir`` is a rename)."""
    real = Path(os.path.realpath(out_dir))
    return real.parent / f".{real.name}.{kind}-{pid}"


def staging_name(out_dir: Path, pid: str) -> Path:
    return _beside(out_dir, "tmp", pid)


@contextlib.contextmanager
def staged(plan: OutputPlan) -> Iterator[Path]:
    """Yield an empty staging folder beside ``plan.out_dir``; on success move what it holds into place.

    On any exception (KeyboardInterrupt included) the staging folder is removed and
    ``out_dir`` is left as it was. The commit moves the names ``plan`` replaces aside,
    moves the new ones in and then deletes the old ones, so a failure part-way puts
    the old ones back.
    """
    out_dir = plan.out_dir
    tmp = staging_name(out_dir, str(os.getpid()))
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as exc:
        raise InputError(f"{out_dir}: cannot write here ({exc.strerror or exc})") from None
    try:
        yield tmp
        commit(plan, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def commit(plan: OutputPlan, tmp: Path) -> list[str]:
    """Move every entry of ``tmp`` into ``plan.out_dir`` by name; return the names written.

    Ctrl-C and SIGTERM wait until the moves are done. If a move fails, the folder is put back as
    it was; if even that fails, the earlier outputs are kept in a folder the error names."""
    out_dir = plan.out_dir
    new = sorted(p.name for p in tmp.iterdir())
    clash = [n for n in new if _exists(out_dir / n) and n not in plan.replace]
    if clash:  # something appeared under an output's name during the work
        raise InputError(f"{out_dir / clash[0]}: exists and was not written by gainfpn; move it away or choose "
                         "another output folder")
    with _signals_held():
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            manifest = read_manifest(out_dir)
            old = _beside(out_dir, "old", str(os.getpid()))
            shutil.rmtree(old, ignore_errors=True)
            old.mkdir()
        except OSError as exc:
            raise InputError(f"{out_dir}: cannot write here ({exc.strerror or exc})") from None
        moved_aside: list[str] = []
        moved_in: list[str] = []
        try:
            for name in sorted(plan.replace):
                if _exists(out_dir / name):
                    os.replace(out_dir / name, old / name)
                    moved_aside.append(name)
            for name in new:
                os.replace(tmp / name, out_dir / name)
                moved_in.append(name)
            for name in moved_aside:
                manifest.pop(name, None)
            manifest.update({name: plan.command for name in new})
            _write_manifest(out_dir, manifest)
        except BaseException as exc:
            _put_back(out_dir, tmp, old, moved_in, moved_aside)
            if isinstance(exc, OSError):
                raise InputError(f"{out_dir}: cannot write here ({exc.strerror or exc})") from None
            raise
        shutil.rmtree(old, ignore_errors=True)
    return new


def _put_back(out_dir: Path, tmp: Path, old: Path, moved_in: list[str], moved_aside: list[str]) -> None:
    """Undo a commit's moves; the earlier outputs' folder is deleted only once they are all back."""
    try:
        for name in moved_in:
            os.replace(out_dir / name, tmp / name)
        for name in moved_aside:
            os.replace(old / name, out_dir / name)
    except OSError as exc:
        raise InputError(f"{out_dir}: could not put the earlier outputs back ({exc.strerror or exc}); they are in "
                         f"{old}") from None
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM are delivered after the block (in the main thread; elsewhere as they come)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def record(out_dir: Path, names: Iterable[str], command: str) -> None:
    """Add ``names`` (written in place by ``command``) to ``out_dir``'s manifest."""
    manifest = read_manifest(out_dir)
    manifest.update({name: command for name in names})
    _write_manifest(out_dir, manifest)


def _write_manifest(out_dir: Path, entries: dict[str, str]) -> None:
    from .files import write_text

    text = json.dumps({"about": "names gainfpn wrote in this folder; --overwrite replaces only these",
                       "entries": dict(sorted(entries.items()))}, indent=1)
    write_text(out_dir / MANIFEST, text)


def remove_staging(out_dir: str | os.PathLike) -> None:
    """Remove the staging folders of ``out_dir`` that processes killed mid-write left behind
    (:func:`staged` removes its own on any exception it sees). A folder of earlier outputs a
    killed commit moved aside is kept: it may be their only copy."""
    real = Path(os.path.realpath(out_dir))
    for stale in real.parent.glob(glob.escape(f".{real.name}.tmp-") + "*"):
        shutil.rmtree(stale, ignore_errors=True)
