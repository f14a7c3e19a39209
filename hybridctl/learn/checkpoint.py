"""Checkpoint directories: written atomically, read with clear errors.

A checkpoint is ONE directory::

    model.pt            torch.save of plain tensors / dicts / numbers only
                        (network and optimizer state dicts, log alpha, RNG state);
                        read back with ``torch.load(..., weights_only=True)``
    config.json         the algorithm, its full config, the system (name, spec overrides, the
                        resolved spec values and their hash: :func:`system_record`), versions
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

Loading checks what the checkpoint was made by and on: :func:`check_algorithm` (SAC does
not load an SSAC checkpoint), :func:`check_plant` (another system, or the same system with
other spec values, is refused naming each differing value; a checkpoint from before the
spec hash was recorded is compared by name and spec overrides, with a warning). Both take
``force=True`` to load anyway, with a warning.
"""

from __future__ import annotations

import dataclasses

import hashlib
import json
import os
import platform
import warnings
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from .. import io as _io
from ..systems import load as load_system
from ..systems.spec import OPTIONAL_DEFAULTS

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


def newest_checkpoint(candidates: Iterable[str | os.PathLike], key: str = "env_steps",
                      strict: bool = False) -> Path | None:
    """Among existing checkpoint directories, the one whose progress.json ``key`` counter (env
    steps, epochs; env steps where it lacks ``key``) is largest: the first on a tie, None if none.

    ``strict`` (resuming): a candidate that exists but is incomplete or unreadable raises
    :class:`CheckpointError` naming it and the missing file, instead of being skipped.
    """
    best, best_count = None, -1
    for cand in candidates:
        cand = Path(cand)
        try:
            found = resolve_checkpoint_dir(cand)
            progress = read_json(found / PROGRESS_FILE)
            count = int(progress.get(key, progress.get("env_steps", 0)))
        except (CheckpointError, TypeError, ValueError, AttributeError) as exc:
            exists = cand.exists() or any(cand.parent.glob(f"{cand.name}.bak-*"))
            if strict and exists:
                raise CheckpointError(f"cannot resume: {exc} (--force resumes from the other checkpoint of the "
                                      f"run folder, if any, or starts anew)") from exc
            continue
        if count > best_count:
            best, best_count = found, count
    return best


# ============================================================================ what a checkpoint was trained on

FORCE_HINT = "pass force=True (CLI: --force) to load it anyway"


def spec_hash(values: dict) -> str:
    """SHA-256 (first 16 hex digits) of the canonical JSON of resolved spec values (sorted keys,
    numpy arrays as lists, no whitespace): equal for equal plants, whatever the override spelling."""
    text = json.dumps(to_jsonable(values), sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def system_record(system) -> dict:
    """config.json's ``system``: name, spec overrides, the resolved spec values and their hash."""
    spec = getattr(system, "spec", None)
    values = to_jsonable(dict(getattr(spec, "values", {}) or {}))
    return {"name": system.name, "overrides": to_jsonable(dict(getattr(spec, "overrides", {}) or {})),
            "spec_hash": spec_hash(values), "spec_values": values}


def _shown(value) -> str:
    return json.dumps(to_jsonable(value))


TRAINING_ONLY_SECTIONS = ("reward.", "initial_state.")
"""Spec keys that shape training but not the plant or its controllers: the reward and the
distribution episodes start from. A deployed policy (:func:`hybridctl.learn.load_controller`)
ignores them; resuming a run does not."""


def plant_differences(found: Path, recorded: dict | None, system,
                      ignore: tuple[str, ...] = ()) -> tuple[list[str], bool]:
    """How the system a checkpoint at ``found`` recorded (config.json ``system``) differs from ``system``.

    Returns (one line per difference, whether the whole spec could be compared). A
    checkpoint without ``spec_hash`` (written before it was recorded) is compared by system
    name and spec overrides only. Keys starting with a prefix in ``ignore`` (e.g.
    :data:`TRAINING_ONLY_SECTIONS`) are not compared.
    """
    recorded = recorded or {}
    name = recorded.get("name")
    if name != system.name:
        return [f"checkpoint {found} was trained on system {name!r}, but this system is {system.name!r}"], True
    current = system_record(system)
    complete = "spec_hash" in recorded
    if not complete:  # an old checkpoint: what its overrides make of today's spec is all there is to compare
        try:
            saved_values = system_record(load_system(name, **(recorded.get("overrides") or {})))["spec_values"]
        except (ValueError, KeyError, TypeError) as exc:
            return [f"checkpoint {found} was trained on {name} with spec overrides "
                    f"{_shown(recorded.get('overrides'))}, which no longer apply ({exc})"], False
    elif recorded["spec_hash"] == current["spec_hash"]:
        return [], True
    else:
        saved_values = recorded.get("spec_values") or {}
    lines = []
    for key in sorted(set(saved_values) | set(current["spec_values"])):
        if key.startswith(ignore) if ignore else False:
            continue
        # a key the other side lacks holds its optional default (a spec key added after the checkpoint)
        absent = OPTIONAL_DEFAULTS.get(key, "(absent)")
        old, new = saved_values.get(key, absent), current["spec_values"].get(key, absent)
        if old != new:
            lines.append(f"checkpoint {found} was trained on {name} with {key}={_shown(old)}; this system has "
                         f"{_shown(new)}")
    if not complete:
        return [f"{line} (an old checkpoint: only its spec overrides are recorded)" for line in lines], False
    return lines, True  # hashes that differ only by optional keys at their defaults: the same plant


def refuse_unless_forced(problems: list[str], force: bool = False) -> bool:
    """Raise :class:`CheckpointError` listing ``problems`` (what does not fit), or with ``force`` warn
    and go on. Returns whether there were any."""
    if not problems:
        return False
    message = "; ".join(problems)
    if not force:
        raise CheckpointError(f"{message} ({FORCE_HINT})")
    warnings.warn(f"force: loading anyway: {message}", stacklevel=3)
    return True


def config_from_meta(config_class: type, meta: dict, overrides: dict | None = None):
    """The ``config_class`` recorded in a checkpoint's config.json (fields it no longer has are
    dropped, so older checkpoints load), with ``overrides`` applied."""
    names = {f.name for f in dataclasses.fields(config_class)}
    return config_class(**{**{k: v for k, v in meta["config"].items() if k in names}, **(overrides or {})})


def check_plant(found: Path, recorded: dict | None, system, force: bool = False,
                ignore: tuple[str, ...] = ()) -> None:
    """Raise :class:`CheckpointError` naming what differs when the checkpoint at ``found`` was trained
    on another plant than ``system`` (``force``: warn instead). An old checkpoint without a spec
    hash is checked by name and overrides, with a warning that nothing more can be checked.
    Keys starting with a prefix in ``ignore`` are not compared."""
    lines, complete = plant_differences(found, recorded, system, ignore)
    if lines:
        message = "; ".join(lines)
        if not force:
            raise CheckpointError(f"{message} ({FORCE_HINT})")
        warnings.warn(f"force: loading anyway: {message}", stacklevel=3)
    if not complete:
        warnings.warn(f"checkpoint {found} records no spec hash (written before hybridctl recorded one): only the "
                      f"system name and spec overrides were checked, nothing more can be checked", stacklevel=3)


def check_algorithm(found: Path, written_by: str | None, accepted: Iterable[str], loader: str,
                    force: bool = False) -> None:
    """Raise :class:`CheckpointError` when the checkpoint at ``found`` was written by another algorithm
    than ``accepted`` (``force``: warn instead; what the classes share is then loaded)."""
    accepted = tuple(accepted)
    if written_by is None or written_by in accepted:
        return
    message = (f"checkpoint {found} was written by {written_by}, not {loader} (use {written_by}.load, or for "
               f"the CLI `hybridctl train {written_by.lower()}`)")
    if not force:
        raise CheckpointError(f"{message}; {FORCE_HINT}")
    warnings.warn(f"force: loading anyway: {message}", stacklevel=3)


def read_model(path: Path, required: Iterable[str] = (), device: str | torch.device = "cpu") -> dict:
    """model.pt at ``path`` (``load_tensors``), raising :class:`CheckpointError` naming the file and
    the keys it lacks when it is not a dict holding every ``required`` key."""
    model = load_tensors(path, device)
    if not isinstance(model, dict):
        raise CheckpointError(f"{path} is damaged: expected a dict of tensors, got {type(model).__name__}")
    missing = [k for k in required if k not in model]
    if missing:
        raise CheckpointError(f"{path} is damaged or not this learner's: it lacks {', '.join(map(repr, missing))}")
    return model
