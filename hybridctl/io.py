"""Files that cannot be half-written: atomic file and directory writes, JSON in and out.

The bottom room of hybridctl: it imports nothing from the package. Every output a
run leaves (trajectories, summaries, checkpoints, meshes, records) goes through
here, so a crash leaves either the old file or the new one, never a torn one. The
lock of a run folder lives here too (:func:`locked_folder`), so that training,
fine-tuning and meshing refuse a folder another run is writing by one mechanism.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

__all__ = ["atomic_write", "atomic_write_text", "write_json", "read_json", "to_jsonable", "atomic_directory",
           "output_folder", "folder_argument", "locked_folder", "LOCK_FILE", "FileFormatError", "RunFolderError",
           "OUTPUT_MARKER", "INPUT_FILES", "input_held", "check_output_folder", "command_folder"]


class FileFormatError(ValueError):
    """A file exists but cannot be read as what it should be (e.g. not valid JSON)."""


class RunFolderError(ValueError):
    """A folder a command cannot write its outputs into: empty, a file, holding a run or an input of the
    command, a checkpoint, or locked by another run (a ValueError: the CLI prints it as one line, exit 2)."""


def to_jsonable(value: Any) -> Any:
    """numpy/torch scalars and arrays, tuples, Paths and non-finite floats -> plain JSON values."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if hasattr(value, "detach") and hasattr(value, "tolist"):  # a torch tensor, without importing torch
        return to_jsonable(value.detach().cpu().tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def atomic_write(path: str | os.PathLike, write: Callable) -> Path:
    """Write ``path`` through a temporary file in the same folder, then rename it into place.

    ``write(f)`` gets the temporary file opened in binary mode. On any error the
    temporary file is removed and an existing ``path`` is left untouched.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    return atomic_write(path, lambda f: f.write(text.encode()))


def write_json(path: str | os.PathLike, data: Any, indent: int = 2) -> Path:
    """Atomically write ``data`` as indented JSON (numpy and torch values converted)."""
    return atomic_write_text(path, json.dumps(to_jsonable(data), indent=indent) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; :class:`FileFormatError` names the file when it is not valid JSON."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{path} is not valid JSON: {exc}") from exc


def folder_argument(path: str | os.PathLike | None, name: str = "--out") -> Path:
    """``path`` (the argument ``name``) as a Path, refusing an empty one.

    ``Path("")`` is the current folder: ``--out ""`` would write a run's outputs next to the
    user's own files, so it raises :class:`RunFolderError` naming ``name`` instead.
    """
    if path is None or not str(path).strip():
        raise RunFolderError(f"{name} is empty: give the folder for the outputs (e.g. {name} runs/NAME)")
    return Path(path)


def output_folder(path: str | os.PathLike, name: str = "--out") -> Path:
    """``path`` as a folder for outputs: created if missing; NotADirectoryError naming ``name`` if it is a
    file, :class:`RunFolderError` if it is empty (:func:`folder_argument`)."""
    path = folder_argument(path, name)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{name} {path} is a file; outputs go into a folder")
    path.mkdir(parents=True, exist_ok=True)
    return path


LOCK_FILE = ".hybridctl.lock"
"""The lock file :func:`locked_folder` holds in a run folder (it keeps the holder's pid)."""

_HELD: dict[Path, tuple[int, int]] = {}
"""Folders this process holds locked: resolved path -> (pid that took the lock, nesting depth)."""


def _lock_holder(fd: int) -> str:
    """The pid written in a lock file held by another process ("unknown" while it has not written it yet)."""
    for _ in range(20):  # the holder writes its pid right after taking the lock: wait a moment for it
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
        if text:
            return text
        time.sleep(0.005)
    return "unknown"


@contextlib.contextmanager
def locked_folder(path: str | os.PathLike, name: str = "--out") -> Iterator[Path]:
    """Hold the folder ``path`` (created if missing) locked while the ``with`` block writes it.

    The lock is an OS file lock (``fcntl.flock``) on :data:`LOCK_FILE` in the folder, which
    holds the pid of its holder. A second holder, in another process, is refused at once with a
    :class:`RunFolderError` "``name`` PATH is locked by pid N ...". The OS drops the lock when its
    process ends, however it ends (kill -9 too), so no stale lock is left to clear by hand; the
    lock file itself stays (removing it would let a late opener lock an unlinked file). Within
    one process the lock nests: a ``with`` inside another on the same folder passes (training
    locks its run folder and the learner's loop locks its log folder). Worker processes forked
    while it is held share it, and it lasts until they end too (they die with their parent).
    """
    path = output_folder(path, name)
    key = path.resolve()
    pid, depth = _HELD.get(key, (None, 0))
    if pid == os.getpid():  # this process holds it already (a fork child inherits the table: pid differs)
        _HELD[key] = (pid, depth + 1)
        try:
            yield path
        finally:
            _HELD[key] = (pid, depth)
        return
    fd = os.open(path / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _lock_holder(fd)
        os.close(fd)
        raise RunFolderError(f"{name} {path} is locked by pid {holder}: another run is writing it; wait until it "
                             f"ends or choose another {name}") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _HELD[key] = (os.getpid(), 1)
        yield path
    finally:
        _HELD.pop(key, None)
        os.close(fd)  # closing the last descriptor releases the flock


OUTPUT_MARKER = ".hybridctl-output"
"""The file :func:`command_folder` leaves in a folder it wrote: the commands that wrote it, one a line."""

INPUT_FILES = (("*.toml", "a spec"), ("*.urdf", "a model file"), ("*.sdf", "a model file"),
               ("*.xml", "a model file"), ("config.json", "a checkpoint"), ("model.pt", "a checkpoint"),
               ("model.zip", "a model file"))
"""Names of the inputs a command must never write beside (glob pattern, what such a file is): specs,
robot descriptions, checkpoints. A folder holding one is someone's input, not an output folder."""


def input_held(path: Path) -> str | None:
    """What input ``path`` (a folder) holds, as "a spec acrobot.toml" (:data:`INPUT_FILES`); None if none."""
    for pattern, what in INPUT_FILES:
        for found in sorted(path.glob(pattern)):
            if found.is_file():
                return f"{what} {found.name}"
    return None


def _made_by(path: Path, command: str, own: tuple[str, ...]) -> bool:
    """Whether ``command`` made the folder ``path``: its :data:`OUTPUT_MARKER` names it, or (a folder written
    before there were markers) it holds every one of ``own``, the command's own record."""
    marker = path / OUTPUT_MARKER
    if marker.is_file() and marker.stat().st_size <= 4096:
        if command in marker.read_text(errors="replace").split():
            return True
    return bool(own) and all((path / name).exists() for name in own)


def check_output_folder(path: str | os.PathLike, command: str, outputs: tuple[str, ...] = (),
                        own: tuple[str, ...] = (), name: str = "--out") -> Path:
    """Refuse (:class:`RunFolderError`, one line naming the folder and what it holds) a folder ``command``
    must not write into; return ``path`` as a Path (it need not exist yet).

    Refused unless ``command`` made the folder (:func:`_made_by`: its marker, or its ``own`` record):
    a folder holding an input (a spec, a model file, a checkpoint: :data:`INPUT_FILES`), and a folder
    holding a file of ``command``'s ``outputs`` that it would replace. A file at ``path`` is a
    NotADirectoryError; an empty ``path`` a RunFolderError (:func:`folder_argument`).
    """
    path = folder_argument(path, name)
    if not path.exists():
        return path
    if not path.is_dir():
        raise NotADirectoryError(f"{name} {path} is a file; outputs go into a folder")
    if _made_by(path, command, own):
        return path
    held = input_held(path)
    if held is not None:
        raise RunFolderError(f"{name} {path} holds {held}, which hybridctl {command} did not write: outputs never go "
                             f"beside an input; choose another {name} (e.g. {name} runs/NAME)")
    clash = [o for o in outputs if (path / o).exists()]
    if clash:
        raise RunFolderError(f"{name} {path} holds {', '.join(clash)}, which hybridctl {command} did not write: it "
                             f"would replace {'them' if len(clash) > 1 else 'it'}; choose another {name}")
    return path


@contextlib.contextmanager
def command_folder(path: str | os.PathLike, command: str, outputs: tuple[str, ...] = (),
                   own: tuple[str, ...] = (), name: str = "--out") -> Iterator[Path]:
    """The output folder of one ``command`` run, checked (:func:`check_output_folder`), created and held
    locked (:func:`locked_folder`: a second run into it, in another process, is refused at once) for
    the ``with`` block, and marked (:data:`OUTPUT_MARKER`) as made by ``command`` so that a later run
    of it may write there again. The check runs before the folder is made and again under the lock."""
    check_output_folder(path, command, outputs, own, name)
    with locked_folder(path, name) as folder:
        check_output_folder(folder, command, outputs, own, name)
        marker = folder / OUTPUT_MARKER
        commands = marker.read_text(errors="replace").split() if marker.is_file() else []
        if command not in commands:
            atomic_write_text(marker, "".join(f"{c}\n" for c in [*commands[:20], command]))
        yield folder


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def atomic_directory(path: str | os.PathLike, write_files: Callable[[Path], None]) -> Path:
    """Atomically (re)place the directory ``path`` with what ``write_files(tmp_dir)`` writes.

    ``write_files`` gets an empty temporary directory next to ``path``; its files are
    fsynced, an existing ``path`` is renamed to ``<path>.bak-XXXX``, the new directory
    is renamed into place and only then is the backup removed. A crash at any point
    leaves the old or the new directory complete (between the two renames, only the
    backup). If ``write_files`` raises, nothing changes.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{target.name}.tmp-", dir=target.parent))
    try:
        write_files(tmp)
        for item in tmp.rglob("*"):
            if item.is_file():
                _fsync_file(item)
        _fsync_dir(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    backup = None
    if target.exists():
        backup = target.parent / f"{target.name}.bak-{uuid.uuid4().hex[:8]}"
        os.replace(target, backup)
    os.replace(tmp, target)
    _fsync_dir(target.parent)
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)
    return target
