"""Checkpoint directories: written atomically, read with clear errors.

A checkpoint is ONE directory::

    model.pt            torch.save of plain tensors / dicts / numbers only
                        (network and optimizer state dicts, log alpha, RNG state);
                        read back with ``torch.load(..., weights_only=True)``
    config.json         the full algorithm config, system name and spec overrides, versions
    normalization.json  observation normalisation ({"type": "none"} when there is none)
    progress.json       env steps, episodes, counters, recent returns, env RNG state
    replay.pt           optional: the replay and needle buffers (oldest first)

:func:`write_checkpoint_dir` writes everything into ``<path>.tmp-XXXX`` next to the
target, fsyncs the files, renames an existing ``<path>`` to ``<path>.bak-XXXX``,
renames the new directory into place and only then removes the backup. A crash at
any point leaves either the old or the new checkpoint complete on disk (between the
two renames, only the backup: :func:`resolve_checkpoint_dir` finds it).
"""

from __future__ import annotations

import json
import math
import os
import platform
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch

MODEL_FILE = "model.pt"
CONFIG_FILE = "config.json"
NORMALIZATION_FILE = "normalization.json"
PROGRESS_FILE = "progress.json"
REPLAY_FILE = "replay.pt"
REQUIRED_FILES = (MODEL_FILE, CONFIG_FILE, NORMALIZATION_FILE, PROGRESS_FILE)
FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint directory is missing, incomplete or does not fit the environment."""


def versions() -> dict[str, str]:
    """Versions of the packages that produced a checkpoint (recorded in config.json)."""
    import gymnasium

    from .. import __version__

    return {"hybridctl": __version__, "torch": torch.__version__, "numpy": np.__version__,
            "gymnasium": gymnasium.__version__, "python": platform.python_version()}


def to_jsonable(value: Any) -> Any:
    """numpy scalars/arrays, tuples, Paths and non-finite floats -> plain JSON values."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, torch.Tensor):
        return to_jsonable(value.detach().cpu().tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


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


def write_json(path: Path, data: dict) -> None:
    """Write ``data`` as indented JSON (numpy and torch values converted)."""
    Path(path).write_text(json.dumps(to_jsonable(data), indent=2) + "\n")


def read_json(path: Path) -> dict:
    """Read a JSON file, naming it in the error when it is not valid JSON."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path} is not valid JSON: {exc}") from exc


def write_checkpoint_dir(path: str | os.PathLike, write_files: Callable[[Path], None]) -> Path:
    """Atomically (re)place the directory ``path`` with what ``write_files(tmp_dir)`` writes.

    ``write_files`` gets an empty temporary directory next to ``path``. If it raises,
    the temporary directory is removed and an existing ``path`` is left untouched.
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


def resolve_checkpoint_dir(path: str | os.PathLike) -> Path:
    """The checkpoint directory at ``path``, or its backup left by an interrupted write.

    Raises :class:`CheckpointError` naming the directory (or the first missing file).
    """
    target = Path(path)
    if not target.exists():
        backups = sorted(target.parent.glob(f"{target.name}.bak-*"), key=lambda p: p.stat().st_mtime)
        if backups:
            target = backups[-1]
        else:
            raise CheckpointError(f"no checkpoint directory at {Path(path)}")
    if not target.is_dir():
        raise CheckpointError(f"checkpoint {target} is not a directory (a checkpoint is a directory "
                              f"holding {', '.join(REQUIRED_FILES)})")
    for name in REQUIRED_FILES:
        if not (target / name).is_file():
            raise CheckpointError(f"checkpoint {target} is incomplete: missing file {name!r} "
                                  f"(expected {', '.join(REQUIRED_FILES)})")
    return target


def load_tensors(path: Path, device: str | torch.device = "cpu") -> dict:
    """``torch.load(path, weights_only=True)`` with the file named in errors."""
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file name
        raise CheckpointError(f"could not read {path}: {type(exc).__name__}: {exc}") from exc


def newest_checkpoint(candidates: Iterable[str | os.PathLike]) -> Path | None:
    """Among existing checkpoint directories, the one with the most env steps (None if none)."""
    best, best_steps = None, -1
    for cand in candidates:
        try:
            found = resolve_checkpoint_dir(cand)
        except CheckpointError:
            continue
        steps = int(read_json(found / PROGRESS_FILE).get("env_steps", 0))
        if steps > best_steps:
            best, best_steps = found, steps
    return best
