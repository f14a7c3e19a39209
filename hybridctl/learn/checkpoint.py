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

Which entries go into which file each learner declares once (``saved``: :class:`Saved` entries);
:class:`Checkpointer` writes and reads them. config.json has one schema for every learner
(:func:`read_meta`; older layouts upgraded by :func:`upgrade_meta`); the file names, the format
number and the JSON shapes are in :mod:`hybridctl.learn.checkpoint_schema`, the system record in
:mod:`hybridctl.learn.plant_record` (both importable from here).

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

Every file of a checkpoint is data from someone else: :func:`read_json` checks the shape of
config.json, progress.json and normalization.json against :data:`SCHEMAS` (one place for every
shape check; an error names the file and the key), and :func:`load_tensors` reads only plain
tensors (no pickled objects) and refuses non-finite weights, naming the file and the tensor.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import platform
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch

from .. import io as _io
from ..limits import MAX_CHECKPOINT_FILE_BYTES, MAX_JSON_BYTES
# the file format's constants and schemas, and the system record, are part of this module's interface
from .checkpoint_schema import (CONFIG_FILE, FORCE_HINT, FORMAT_VERSION, MODEL_FILE, NORMALIZATION_FILE,  # noqa: F401
                                PROGRESS_FILE, REPLAY_FILE, REQUIRED_FILES, SCHEMAS, CheckpointError, _shown_short,
                                check_env_kwargs, check_schema, require_keys)
from .plant_record import (GATE_SECTION, TRAINING_ONLY_SECTIONS, check_plant, env_record,  # noqa: F401
                           plant_differences, recorded_system, spec_hash, system_record)


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
    """Read a JSON file of a checkpoint, naming it in the error when it is not valid JSON.

    config.json, progress.json and normalization.json are also checked against :data:`SCHEMAS`
    (:func:`check_schema`), so a loader may index what the schema guarantees. Files over
    :data:`~hybridctl.limits.MAX_JSON_BYTES` are refused before reading.
    """
    path = Path(path)
    check_regular_file(path, MAX_JSON_BYTES, "MAX_JSON_BYTES", "a JSON file")
    try:
        doc = _io.read_json(path)
    except _io.FileFormatError as exc:
        raise CheckpointError(str(exc)) from exc
    except UnicodeDecodeError:
        raise CheckpointError(f"{path} is not valid JSON: not UTF-8 text") from None
    except RecursionError:
        raise CheckpointError(f"{path} is not valid JSON: arrays or objects nested too deeply") from None
    if path.name in SCHEMAS:
        check_schema(path, doc)
    return doc


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


def check_regular_file(path: Path, limit: int | None = None,
                       limit_name: str = "MAX_CHECKPOINT_FILE_BYTES", what: str = "a checkpoint file") -> None:
    """Raise :class:`CheckpointError` naming ``path`` unless it is a regular file (a link to one counts) of at
    most ``limit`` bytes (default MAX_CHECKPOINT_FILE_BYTES): checked with ``os.stat`` before it is opened, so a device (``/dev/zero``), a FIFO or
    a folder is never read, and a file too large for its kind is refused before a byte is read."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such file") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(info.st_mode):
        raise CheckpointError(f"{path} is not a regular file (a device, a FIFO or a folder): {what} is never read "
                              f"from one")
    limit = MAX_CHECKPOINT_FILE_BYTES if limit is None else limit
    if info.st_size > limit:
        raise CheckpointError(f"{path} has {info.st_size:,} bytes, above the limit of {limit:,} for {what} "
                              f"(hybridctl.limits.{limit_name})")


def load_tensors(path: Path, device: str | torch.device = "cpu") -> dict:
    """``torch.load(path, weights_only=True)`` with the file named in errors.

    A file holding pickled Python objects (anything but tensors, numbers, strings and
    containers of them) is refused, never unpickled; a floating-point tensor holding NaN or
    Inf is refused naming the tensor (:func:`check_finite_tensors`).
    """
    check_regular_file(path)
    try:
        content = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file name, without torch's advice
        text = str(exc)
        if isinstance(exc, pickle.UnpicklingError) and "Unsupported global" in text:
            # torch's weights-only unpickler met an object it does not allow; its message advises
            # weights_only=False, which would run the object's code: never say that
            raise CheckpointError(f"{path} holds pickled Python objects, which hybridctl refuses to load (a "
                                  f"checkpoint file holds only tensors, numbers and dicts of them)") from None
        raise CheckpointError(f"could not read {path}: it is damaged or not a torch file "
                              f"({_load_failure(exc)})") from None
    check_finite_tensors(path, content)
    return content


def _load_failure(exc: Exception) -> str:
    """The reason of a failed ``torch.load`` in a few words (the unpickler's own error, not its advice)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for i, line in enumerate(lines):
        if "WeightsUnpickler error:" in line:
            detail = line.partition("WeightsUnpickler error:")[2].strip() or (lines[i + 1] if i + 1 < len(lines) else "")
            return f"not a tensor file: {detail}"
    first = lines[0] if lines else type(exc).__name__
    return f"{type(exc).__name__}: {first}" if "weights_only" not in first else type(exc).__name__


def check_finite_tensors(path: Path, content: Any, where: str = "") -> None:
    """Raise :class:`CheckpointError` naming ``path`` and the key of the first floating-point tensor in
    ``content`` (nested dicts and lists) that holds NaN or Inf: weights, statistics and data sets
    of a checkpoint are finite, and a non-finite one would surface only later, far from the file."""
    if isinstance(content, torch.Tensor):
        if (content.is_floating_point() or content.is_complex()) and not bool(torch.isfinite(content).all()):
            raise CheckpointError(f"{path}: tensor {where or '(the file)'!r} holds NaN or Inf; the checkpoint is "
                                  f"damaged (weights and statistics must be finite)")
        return
    if isinstance(content, dict):
        for key, value in content.items():
            check_finite_tensors(path, value, f"{where}.{key}" if where else str(key))
    elif isinstance(content, (list, tuple)):
        for i, value in enumerate(content):
            check_finite_tensors(path, value, f"{where}[{i}]")


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


# ============================================================================ loading: algorithm and config


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


def config_from_meta(config_class: type, meta: dict, overrides: dict | None = None, found: Path | None = None):
    """The ``config_class`` recorded in a checkpoint's config.json (renamed fields mapped by the
    class's ``upgrade_recorded`` when it has one; fields it no longer has are dropped with a
    warning naming them, so older checkpoints load), validated, with ``overrides`` applied.

    A recorded value the config refuses raises :class:`CheckpointError` naming the file (the
    checkpoint at ``found``) and the field; an override it refuses stays the caller's ValueError.
    """
    names = {f.name for f in dataclasses.fields(config_class)}
    where = found / CONFIG_FILE if found is not None else CONFIG_FILE
    if not isinstance(meta.get("config"), dict):
        raise CheckpointError(f"{where}: 'config' must be an object {{...}}, got {_shown_short(meta.get('config'))}")
    recorded = meta["config"]
    if hasattr(config_class, "upgrade_recorded"):   # the config's own renamed fields (APG's ray_address)
        recorded = config_class.upgrade_recorded(recorded)
    dropped = sorted(set(recorded) - names)
    if dropped:
        warnings.warn(f"{where}: {config_class.__name__} no longer has the recorded field(s) {dropped}: "
                      f"loaded without them", UserWarning, stacklevel=2)
    if overrides and "device" in overrides and "device" in recorded:
        # a run trained on a GPU loads on a machine without one when the caller names another device:
        # the recorded device is not checked against this machine's
        recorded = {**recorded, "device": overrides["device"]}
    try:
        config = config_class(**{k: v for k, v in recorded.items() if k in names})
        if hasattr(config, "validate"):
            config.validate()
    except (TypeError, ValueError, OverflowError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointError(f"{where}: 'config' holds a value {config_class.__name__} refuses: {reason}") from None
    if not overrides:
        return config
    config = dataclasses.replace(config, **overrides)
    if hasattr(config, "validate"):
        config.validate()
    return config


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


# ============================================================================ config.json: one schema


def upgrade_meta(meta: dict) -> dict:
    """config.json ``meta`` in today's layout (:data:`FORMAT_VERSION`): ``system`` a record.

    Format 1 checkpoints load unchanged on disk: APG's bare ``system`` name becomes its
    ``plant`` record with ``system_overrides`` as its overrides (the reward settings are the
    config's, re-applied on load); ARS's and fine-tuning's ``env`` / ``env_kwargs`` become an
    :func:`env_record` (an ARS run on a hybridctl system keeps its system record and gains
    ``kwargs``).
    """
    meta = dict(meta)
    system = meta.get("system")
    if isinstance(system, str):
        record = dict(meta.pop("plant", None) or {"name": system})
        record["name"] = system
        record["overrides"] = meta.pop("system_overrides", record.get("overrides") or {})
        meta["system"] = record
    if "env" in meta:
        env, kwargs = meta.pop("env"), meta.pop("env_kwargs", None)   # kwargs: checked where they are read
        if isinstance(meta.get("system"), dict):
            meta["system"] = {**meta["system"], "kwargs": {} if kwargs is None else kwargs}
        else:
            meta["system"] = {"name": env, "kind": "gymnasium", "kwargs": {} if kwargs is None else kwargs}
    return meta


def read_meta(found: Path) -> dict:
    """config.json of the checkpoint directory ``found``, shape-checked (:data:`SCHEMAS`) and in
    today's layout (:func:`upgrade_meta`); :class:`CheckpointError` naming the file otherwise."""
    meta = read_json(found / CONFIG_FILE)
    if not isinstance(meta, dict) or not isinstance(meta.get("config", {}), dict):
        raise CheckpointError(f"{found / CONFIG_FILE} is damaged: expected an object with 'algorithm' and 'config'")
    return upgrade_meta(meta)


# ============================================================================ declared checkpoint state


@dataclass(frozen=True)
class Saved:
    """One entry of a learner's checkpoint: where it lives in which file, and how it is restored.

    ``key``: dotted path inside the file (``"extra.gate"`` is ``model["extra"]["gate"]``);
    ``""`` means the entry is the whole file. ``attr``: dotted attribute path on the
    learner (``"stats.sum"``). ``kind``:

    * ``"state"``: an object with ``state_dict`` / ``load_state_dict`` (modules, optimizers, buffers);
    * ``"rng"``: a ``torch.Generator`` (``get_state`` / ``set_state``);
    * ``"param"``: a tensor restored in place (``log_alpha``: the optimizer holds it);
    * ``"tensor"``: a tensor attribute replaced on load;
    * ``"array"``: a numpy array stored as a tensor, restored as a float64 copy;
    * ``"value"``: a number / list / dict (JSON in progress.json), with optional converters.

    ``bulky`` entries (replay, gate data) are written only with ``include_bulky`` and
    read only on resume. ``restore=False``: written for readers, never read back.
    ``optional``: missing on disk (older checkpoints) or None on the learner is fine.
    """

    key: str
    attr: str
    kind: str = "value"
    file: str = MODEL_FILE
    bulky: bool = False
    optional: bool = False
    restore: bool = True
    save: Callable | None = None
    load: Callable | None = None


def _get_attr(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set_attr(obj, path: str, value) -> None:
    *parents, last = path.split(".")
    for part in parents:
        obj = getattr(obj, part)
    setattr(obj, last, value)


def _put(tree: dict, key: str, value) -> None:
    if key == "":
        tree.update(value)
        return
    *parents, last = key.split(".")
    for part in parents:
        tree = tree.setdefault(part, {})
    tree[last] = value


_MISSING = object()


def _take(tree: dict, key: str):
    if key == "":
        return tree
    for part in key.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return _MISSING
        tree = tree[part]
    return tree


class Checkpointer:
    """Writes and restores a learner's checkpoint directory from its declared ``saved`` entries."""

    def __init__(self, learner: "Learner"):
        self.learner = learner

    def save(self, path: str | Path, include_bulky: bool = False) -> Path:
        """Write the checkpoint directory ``path`` atomically (the old one stays until the new is complete)."""
        learner = self.learner
        learner.before_checkpoint()

        def write(d: Path) -> None:
            files: dict[str, dict] = {MODEL_FILE: {"format": FORMAT_VERSION}, PROGRESS_FILE: {}}
            for item in learner.saved:
                if item.bulky and not include_bulky:
                    continue
                value = _get_attr(learner, item.attr)
                if value is None:
                    if item.optional:
                        continue
                    raise CheckpointError(f"{learner.algorithm_name}: {item.attr} is None, cannot save {item.key!r}")
                _put(files.setdefault(item.file, {}), item.key, self._dump(item, value))
            for name, content in files.items():
                if name.endswith(".json"):
                    write_json(d / name, content)
                else:
                    torch.save(content, d / name)
            write_json(d / CONFIG_FILE, {**learner.checkpoint_meta(), "format": FORMAT_VERSION,
                                              "files": sorted({*files, CONFIG_FILE, NORMALIZATION_FILE}),
                                              "versions": versions()})
            write_json(d / NORMALIZATION_FILE, learner.normalization())

        return write_checkpoint_dir(path, write)

    @staticmethod
    def _dump(item: Saved, value):
        if item.save is not None:
            value = item.save(value)
        if item.kind == "state":
            return value.state_dict()
        if item.kind == "rng":
            return value.get_state()
        if item.kind in ("param", "tensor"):
            return value.detach().clone()
        if item.kind == "array":
            return torch.as_tensor(np.asarray(value))
        return value

    def restore(self, path: str | Path, bulky: bool = False, force: bool = False) -> Path:
        """Load the entries of the checkpoint at ``path`` (bulky ones too if ``bulky``) into the learner.

        Every file an entry lives in is read and checked: a missing, damaged or incomplete
        one raises :class:`CheckpointError` naming it (and the entry it lacks), as does a
        checkpoint written by another algorithm or on another plant
        (:meth:`Learner.check_checkpoint`). ``force``: another algorithm or plant is loaded
        with a warning (what the classes share), and a resume continues without a missing
        or damaged bulky file (replay, gate data), saying so.
        """
        learner = self.learner
        found = resolve_checkpoint_dir(path)
        meta = read_meta(found)
        check_algorithm(found, meta.get("algorithm"), learner.compatible_algorithms, learner.algorithm_name, force)
        normalization = read_json(found / NORMALIZATION_FILE)
        if not isinstance(normalization, dict) or "type" not in normalization:
            raise CheckpointError(f"{found / NORMALIZATION_FILE} is damaged: expected an object with 'type'")
        learner.check_checkpoint(found, meta, normalization, force=force)
        cache: dict[str, Any] = {}
        for item in learner.saved:
            if not item.restore or (item.bulky and not bulky):
                continue
            if item.file not in cache:
                cache[item.file] = self._read(found, item.file, force, meta)
            content = cache[item.file]
            if content is None:  # a bulky file that was not saved
                continue
            value = _take(content, item.key)
            if value is _MISSING:
                if item.optional:
                    continue
                raise CheckpointError(f"{found / item.file} lacks {item.key!r}")
            try:
                self._load(item, value)
            except CheckpointError:
                raise
            except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as exc:
                raise CheckpointError(f"{found / item.file}: {item.key or 'its content'!r} does not fit this "
                                      f"{learner.algorithm_name} ({type(exc).__name__}: {exc})") from exc
        learner.after_restore(found, meta, bulky)
        return found

    def missing_bulky(self, found: Path, meta: dict) -> list[tuple[str, bool]]:
        """The bulky files (replay, gate data) the checkpoint at ``found`` lacks, each with whether it
        should be there: config.json's ``files`` lists what was written (older checkpoints: the
        bulky files are expected unless their config had ``save_replay`` False)."""
        written = meta.get("files")
        out = []
        for name in dict.fromkeys(i.file for i in self.learner.saved if i.bulky):
            if not (found / name).is_file():
                expected = name in written if isinstance(written, list) else \
                    bool((meta.get("config") or {}).get("save_replay", True))
                out.append((name, expected))
        return out

    def check_resumable(self, path: str | Path, force: bool = False) -> Path:
        """Raise :class:`CheckpointError` when a resume from ``path`` would lack a replay / gate data
        file the checkpoint should hold (``force``: no error; the resume then says so)."""
        found = resolve_checkpoint_dir(path)
        meta = read_json(found / CONFIG_FILE)
        for name, expected in self.missing_bulky(found, meta if isinstance(meta, dict) else {}):
            if expected and not force:
                raise CheckpointError(self._missing_message(found, name))
        return found

    def _missing_message(self, found: Path, name: str) -> str:
        return (f"cannot resume from {found}: missing file {name!r} ({', '.join(self._entries(name))}); a resumed run "
                f"without it would not be the same run. --force (force=True) resumes without it")

    def _entries(self, name: str) -> list[str]:
        return [i.attr.lstrip("_") for i in self.learner.saved if i.file == name]

    def _read(self, found: Path, name: str, force: bool = False, meta: dict | None = None):
        path = found / name
        bulky = name not in REQUIRED_FILES
        keys = self._entries(name)
        if not path.is_file():
            if not bulky:
                raise CheckpointError(f"checkpoint {found} is incomplete: missing file {name!r}")
            expected = dict(self.missing_bulky(found, meta or {})).get(name, True)
            if not expected:  # saved without it on purpose (save_replay=False, save(include_replay=False))
                warnings.warn(f"{found} was saved without {name} (save_replay=False or save(include_replay=False)): "
                              f"the resumed run starts without {', '.join(keys)}", stacklevel=4)
                return None
            if not force:
                raise CheckpointError(self._missing_message(found, name))
            warnings.warn(f"force: {found} has no {name}: the resumed run starts without {', '.join(keys)}",
                          stacklevel=4)
            return None
        try:
            content = read_json(path) if name.endswith(".json") else load_tensors(
                path, getattr(self.learner, "device", "cpu"))
            if not isinstance(content, dict):
                raise CheckpointError(f"{path} is damaged: expected a dict, got {type(content).__name__}")
        except CheckpointError as exc:
            if not (bulky and force):
                raise
            warnings.warn(f"force: {exc}; the resumed run starts without {', '.join(keys)}", stacklevel=4)
            return None
        return content

    def _load(self, item: Saved, value) -> None:
        learner = self.learner
        if item.kind == "state":
            target = _get_attr(learner, item.attr)
            if item.optional and (target is None or not value):  # e.g. no alpha optimizer (fixed alpha)
                return
            target.load_state_dict(value)
            return
        if item.kind == "rng":
            _get_attr(learner, item.attr).set_state(value.cpu())
            return
        if item.kind == "param":
            with torch.no_grad():
                _get_attr(learner, item.attr).copy_(value)
            return
        if item.kind == "tensor":
            current = _get_attr(learner, item.attr)
            value = value.to(dtype=current.dtype, device=current.device)
        elif item.kind == "array":
            value = value.double().numpy().copy()
        if item.load is not None:
            value = item.load(value)
        _set_attr(learner, item.attr, value)
