"""Files that cannot be half-written: atomic file and directory writes, JSON in and out.

The bottom room of hybridctl: it imports nothing from the package. Every output a
run leaves (trajectories, summaries, checkpoints, meshes, records) goes through
here, so a crash leaves either the old file or the new one, never a torn one.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["atomic_write", "atomic_write_text", "write_json", "read_json", "to_jsonable", "atomic_directory",
           "output_folder", "FileFormatError"]


class FileFormatError(ValueError):
    """A file exists but cannot be read as what it should be (e.g. not valid JSON)."""


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


def output_folder(path: str | os.PathLike, name: str = "--out") -> Path:
    """``path`` as a folder for outputs: created if missing; NotADirectoryError naming ``name`` if it is a file."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{name} {path} is a file; outputs go into a folder")
    path.mkdir(parents=True, exist_ok=True)
    return path


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
