"""Checkpoint directories: written atomically, read with clear errors.

A checkpoint is ONE directory::

    model.pt            torch.save of plain tensors / dicts / numbers only
                        (network and optimizer state dicts, log alpha, RNG state);
                        read back with ``torch.load(..., weights_only=True)``
    config.json         the full algorithm config, system name and spec overrides, versions
    normalization.json  observation normalisation ({"type": "none"} when there is none)
    progress.json       env steps, episodes, counters, recent returns, env RNG state
    replay.pt           optional: the replay and needle buffers (oldest first)
    gate_data.pt        optional (SSAC): the gate data set and the states waiting to be relabelled

Which entries go into which file each learner declares once (``saved``, see
:mod:`hybridctl.learn.run`); :class:`~hybridctl.learn.run.Checkpointer` writes and reads them.

:func:`write_checkpoint_dir` writes everything into ``<path>.tmp-XXXX`` next to the
target, fsyncs the files, renames an existing ``<path>`` to ``<path>.bak-XXXX``,
renames the new directory into place and only then removes the backup. A crash at
any point leaves either the old or the new checkpoint complete on disk (between the
two renames, only the backup: :func:`resolve_checkpoint_dir` finds it).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from .. import io as _io

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


def write_json(path: Path, data: dict) -> None:
    """Atomically write ``data`` as indented JSON (numpy and torch values converted)."""
    _io.write_json(path, data)


def read_json(path: Path) -> dict:
    """Read a JSON file, naming it in the error when it is not valid JSON."""
    try:
        return _io.read_json(path)
    except _io.FileFormatError as exc:
        raise CheckpointError(str(exc)) from exc


write_checkpoint_dir = _io.atomic_directory
to_jsonable = _io.to_jsonable


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


def newest_checkpoint(candidates: Iterable[str | os.PathLike], key: str = "env_steps") -> Path | None:
    """Among existing checkpoint directories, the one whose progress.json ``key`` counter (env
    steps, epochs; env steps where it lacks ``key``) is largest: the first on a tie, None if none."""
    best, best_count = None, -1
    for cand in candidates:
        try:
            found = resolve_checkpoint_dir(cand)
        except CheckpointError:
            continue
        progress = read_json(found / PROGRESS_FILE)
        count = int(progress.get(key, progress.get("env_steps", 0)))
        if count > best_count:
            best, best_count = found, count
    return best
