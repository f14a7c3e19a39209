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

Every file of a checkpoint is data from someone else: :func:`read_json` checks the shape of
config.json, progress.json and normalization.json against :data:`SCHEMAS` (one place for every
shape check; an error names the file and the key), and :func:`load_tensors` reads only plain
tensors (no pickled objects) and refuses non-finite weights, naming the file and the tensor.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import hashlib
import json
import math
import numbers
import os
import pickle
import platform
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch

from .. import io as _io
from ..limits import MAX_HIDDEN_UNITS, MAX_JSON_BYTES, MAX_NUM_ENVS
from ..systems import load as load_system
from ..systems.spec import OPTIONAL_DEFAULTS, SYSTEM_NAME

MODEL_FILE = "model.pt"
CONFIG_FILE = "config.json"
NORMALIZATION_FILE = "normalization.json"
PROGRESS_FILE = "progress.json"
REPLAY_FILE = "replay.pt"
REQUIRED_FILES = (MODEL_FILE, CONFIG_FILE, NORMALIZATION_FILE, PROGRESS_FILE)
FORMAT_VERSION = 2
"""config.json's layout: 2 -- every learner records what it trained on as ``system`` (a record, see
:func:`system_record` and :func:`env_record`); 1 -- APG recorded a bare name with ``plant`` and
``system_overrides`` beside it, ARS and fine-tuning ``env`` and ``env_kwargs`` (:func:`upgrade_meta`
reads both)."""


class CheckpointError(RuntimeError):
    """A checkpoint directory is missing, incomplete or does not fit the environment.

    Its text is always one line: a wrapped error's further lines (torch's ``load_state_dict``
    lists every key) are joined with "; ", so the CLI prints one ``error:`` line."""

    def __str__(self) -> str:
        text = super().__str__()
        return "; ".join(line.strip() for line in text.splitlines() if line.strip()) if "\n" in text else text


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
    if path.is_file() and path.stat().st_size > MAX_JSON_BYTES:
        raise CheckpointError(f"{path} has {path.stat().st_size:,} bytes, above the limit of {MAX_JSON_BYTES:,} "
                              f"for a JSON file (hybridctl.limits.MAX_JSON_BYTES)")
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


def load_tensors(path: Path, device: str | torch.device = "cpu") -> dict:
    """``torch.load(path, weights_only=True)`` with the file named in errors.

    A file holding pickled Python objects (anything but tensors, numbers, strings and
    containers of them) is refused, never unpickled; a floating-point tensor holding NaN or
    Inf is refused naming the tensor (:func:`check_finite_tensors`).
    """
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


# ============================================================================ the shape of the JSON files
MAX_COUNT = 2 ** 53
"""The largest counter (env steps, episodes, dimensions) a checkpoint may record: the largest
integer float64 holds exactly; a larger one is damage, not progress."""
MAX_HIDDEN_LAYERS = 64
"""Hidden layers of a recorded network (config ``hidden_layers``, ``gate.hidden``): far above any
learner's default (2), low enough that a damaged value cannot ask for unbounded work."""


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value) -> bool:
    """A finite number or a (nested) list of them."""
    if isinstance(value, list):
        return all(_numbers(v) for v in value)
    return _is_number(value)


def _check(test: Callable[[Any], bool], wants: str) -> tuple[Callable[[Any], bool], str]:
    return test, wants


STRING = _check(lambda v: isinstance(v, str), "a string")
OBJECT = _check(lambda v: isinstance(v, dict), "an object {...}")
LIST = _check(lambda v: isinstance(v, list), "a list")
BOOL = _check(lambda v: isinstance(v, bool), "true or false")
NUMBER = _check(_is_number, "a finite number")
NUMBER_OR_NULL = _check(lambda v: v is None or _is_number(v), "a finite number or null")
NUMBERS = _check(lambda v: isinstance(v, list) and _numbers(v), "a list of finite numbers")
COUNT = _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_COUNT,
               "an integer in [0, 2**53]")
POSITIVE_COUNT = _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_COUNT,
                        "an integer in [1, 2**53]")
WIDTH = _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_HIDDEN_UNITS,
               f"an integer in [1, {MAX_HIDDEN_UNITS}] (hybridctl.limits.MAX_HIDDEN_UNITS)")
LAYERS = _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_HIDDEN_LAYERS,
                f"an integer in [1, {MAX_HIDDEN_LAYERS}]")
WIDTHS = _check(lambda v: isinstance(v, list) and 1 <= len(v) <= MAX_HIDDEN_LAYERS and all(WIDTH[0](w) for w in v),
                f"a list of 1 to {MAX_HIDDEN_LAYERS} integers in [1, {MAX_HIDDEN_UNITS}]")
UINT128 = _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 128,
                 "an integer in [0, 2**128)")
STRINGS = _check(lambda v: isinstance(v, list) and all(isinstance(s, str) for s in v), "a list of strings")
# a running mean/std's sample count: SB3's VecNormalize keeps a float (it starts at epsilon = 1e-4)
SAMPLE_COUNT = _check(lambda v: _is_number(v) and 0 <= v <= MAX_COUNT, "a finite number in [0, 2**53]")
INTEGERS = _check(lambda v: isinstance(v, list) and all(COUNT[0](i) for i in v), "a list of integers >= 0")

# a recorded system is a name, never a path to some other spec file (systems.load reads a path)
SYSTEM = _check(lambda v: isinstance(v, str) and SYSTEM_NAME.fullmatch(v) is not None,
                "a system name such as 'acrobot' ([a-z0-9_-], not a path)")
_SYSTEM_RECORD = {"name": SYSTEM, "overrides": OBJECT, "spec_hash": STRING, "spec_values": OBJECT,
                  "recorded": STRING}
SYSTEM_OR_RECORD = _check(lambda v: isinstance(v, dict) or SYSTEM[0](v),
                          "a system record {...} (a bare system name in checkpoints before format 2)")
_VECTOR_AGENT = {  # SAC and SSAC (learn/vector_agent.py)
    "system": OBJECT, **{f"system.{k}": v for k, v in _SYSTEM_RECORD.items()},
    "obs_dim": POSITIVE_COUNT, "action_dim": POSITIVE_COUNT, "action_scale": NUMBERS,
    "decision_period": NUMBER_OR_NULL,
    # the config fields load_controller builds the deployed actor from
    "config.hidden_layers": LAYERS, "config.hidden_size": WIDTH, "config.log_std_min": NUMBER,
    "config.log_std_max": NUMBER, "config.obs_transform": STRING, "config.gate_cost_feature": BOOL,
    "config.num_envs": _check(lambda v: POSITIVE_COUNT[0](v) and v <= MAX_NUM_ENVS,
                              f"an integer in [1, {MAX_NUM_ENVS:,}] (hybridctl.limits.MAX_NUM_ENVS)"),
}
_VECTOR_AGENT_REQUIRED = ("config", "system", "system.name", "obs_dim", "action_dim")
SCHEMAS: dict[str, dict[str | None, tuple[dict, tuple]]] = {
    # file -> algorithm (None: every algorithm) -> (key -> (test, what it must be), required keys).
    # A key is 'a.b' for b inside object a. read_json checks the types of the keys present and the
    # keys every algorithm needs (None); a loader checks its algorithm's required keys (require_keys)
    # after it has checked the algorithm, so that another algorithm's checkpoint is named as such.
    "config.json": {
        None: ({"algorithm": STRING, "format": COUNT, "config": OBJECT, "versions": OBJECT, "files": STRINGS},
               ("config",)),
        "SAC": (_VECTOR_AGENT, _VECTOR_AGENT_REQUIRED),
        "SSAC": ({**_VECTOR_AGENT, "gate": OBJECT, "gate.hidden": WIDTHS, "gate.cost_feature": BOOL,
                  "gate.gate_on": NUMBER, "gate.gate_off": NUMBER, "gate.K": NUMBERS, "gate.info": OBJECT},
                 (*_VECTOR_AGENT_REQUIRED, "gate")),
        "APG": ({"method": STRING, "system": SYSTEM_OR_RECORD, **{f"system.{k}": v for k, v in _SYSTEM_RECORD.items()},
                 "system_overrides": OBJECT, "plant": OBJECT, **{f"plant.{k}": v for k, v in _SYSTEM_RECORD.items()},
                 "policy": OBJECT, "policy.kind": STRING, "policy.obs_dim": POSITIVE_COUNT,
                 "policy.act_dim": POSITIVE_COUNT, "policy.hidden": _check(
                     lambda v: isinstance(v, list) and len(v) <= MAX_HIDDEN_LAYERS and all(WIDTH[0](w) for w in v),
                     f"a list of at most {MAX_HIDDEN_LAYERS} integers in [1, {MAX_HIDDEN_UNITS}]"),
                 "policy.action_limit": NUMBER, "policy.n_params": COUNT, "policy.hidden_state": COUNT,
                 "substeps": POSITIVE_COUNT, "period": NUMBER,
                 "config.population": POSITIVE_COUNT, "config.horizon": POSITIVE_COUNT},
                ("system", "config")),
    },
    "progress.json": {None: ({**{k: COUNT for k in (
        "env_steps", "episodes", "gradient_steps", "updates", "rounds", "needle_episodes", "needle_size",
        "replay_size", "epoch", "iterations", "nan_grads", "large_grads")},
        "wall_time": NUMBER, **{k: NUMBER_OR_NULL for k in ("mean_return", "best_mean_return", "success_rate")},
        "recent_returns": LIST, "recent_successes": LIST, "history": LIST,
        # numpy's PCG64 state (128-bit integers): what Generator.bit_generator.state accepts
        "env_rng_state": OBJECT, "env_rng_state.bit_generator": _check(lambda v: v == "PCG64", "'PCG64'"),
        "env_rng_state.state": OBJECT, **{f"env_rng_state.state.{k}": UINT128 for k in ("state", "inc")},
        "env_rng_state.has_uint32": _check(lambda v: v in (0, 1) and not isinstance(v, bool), "0 or 1"),
        "env_rng_state.uinteger": _check(lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 32,
                                         "an integer in [0, 2**32)")}, ())},
    "normalization.json": {None: ({"type": STRING, "mean": NUMBERS, "std": NUMBERS, "count": SAMPLE_COUNT,
                                   "n_states": POSITIVE_COUNT, "angle_indices": INTEGERS, "features": STRING},
                                  ("type",))},
}
"""What each key of a checkpoint's JSON files must be: one place for every shape check."""

_ABSENT = object()


def _lookup(doc: dict, key: str):
    for part in key.split("."):
        if not isinstance(doc, dict) or part not in doc:
            return _ABSENT
        doc = doc[part]
    return doc


def check_schema(path: Path, doc: Any) -> None:
    """Raise :class:`CheckpointError` naming ``path`` and the key when ``doc`` (the parsed JSON file at
    ``path``) does not have the shape :data:`SCHEMAS` gives for its file name (and, for config.json,
    its ``algorithm``). Keys the schema does not name are not checked."""
    tables = SCHEMAS.get(Path(path).name)
    if tables is None:
        return
    if not isinstance(doc, dict):
        raise CheckpointError(f"{path} is damaged: expected an object {{...}}, got {_kind(doc)}")
    _require(path, doc, tables[None][1])
    algorithm = doc.get("algorithm")
    for algo in (None, algorithm if isinstance(algorithm, str) and algorithm in tables else None):
        for key, (test, wants) in tables[algo][0].items():
            value = _lookup(doc, key)
            if value is not _ABSENT and not test(value):
                raise CheckpointError(f"{path}: {key!r} must be {wants}, got {_shown_short(value)}")


def require_keys(found: Path, meta: dict, algorithm: str) -> None:
    """Raise :class:`CheckpointError` naming the file and key when the config.json ``meta`` of the
    checkpoint at ``found`` lacks a key :data:`SCHEMAS` requires of an ``algorithm`` checkpoint."""
    _require(found / CONFIG_FILE, meta, SCHEMAS[CONFIG_FILE].get(algorithm, ({}, ()))[1])


def _require(path: Path, doc: dict, keys: Iterable[str]) -> None:
    for key in keys:
        if _lookup(doc, key) is _ABSENT:
            raise CheckpointError(f"{path} is damaged or not this learner's: it lacks the key {key!r}")


def _kind(value) -> str:
    return {list: "a list", type(None): "null", str: "a string", bool: "a boolean", int: "a number",
            float: "a number", dict: "an object"}.get(type(value), type(value).__name__)


def _shown_short(value) -> str:
    text = json.dumps(to_jsonable(value)) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."



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


TRAINING_ONLY_SECTIONS = ("reward.", "initial_state.", "episode.")
"""Spec keys that shape training but not the plant or its controllers: the reward, the
distribution episodes start from and how long training episodes last. A deployed policy
(:func:`hybridctl.learn.load_controller`) ignores them; resuming a run does not."""

GATE_SECTION = "gate."
"""Spec keys only a learned gate uses (its cost feature's scale, its warm-start spreads and
labels): ignored when only the swing-up policy of a checkpoint is deployed."""


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


def config_from_meta(config_class: type, meta: dict, overrides: dict | None = None, found: Path | None = None):
    """The ``config_class`` recorded in a checkpoint's config.json (fields it no longer has are
    dropped with a warning naming them, so older checkpoints load), validated, with ``overrides`` applied.

    A recorded value the config refuses raises :class:`CheckpointError` naming the file (the
    checkpoint at ``found``) and the field; an override it refuses stays the caller's ValueError.
    """
    names = {f.name for f in dataclasses.fields(config_class)}
    where = found / CONFIG_FILE if found is not None else CONFIG_FILE
    if not isinstance(meta.get("config"), dict):
        raise CheckpointError(f"{where}: 'config' must be an object {{...}}, got {_shown_short(meta.get('config'))}")
    dropped = sorted(set(meta["config"]) - names)
    if dropped:
        warnings.warn(f"{where}: {config_class.__name__} no longer has the recorded field(s) {dropped}: "
                      f"loaded without them", UserWarning, stacklevel=2)
    try:
        config = config_class(**{k: v for k, v in meta["config"].items() if k in names})
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


def recorded_system(found: Path, name: str, overrides: dict):
    """The system a checkpoint at ``found`` records (its name and spec overrides in config.json), or
    :class:`CheckpointError` naming the file when that system is unknown here or its overrides do
    not apply (the spec's own message says which value)."""
    try:
        return load_system(name, **overrides)
    except KeyError as exc:
        raise CheckpointError(f"{found / CONFIG_FILE}: {exc.args[0] if exc.args else exc}") from None
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{found / CONFIG_FILE}: the recorded system {name!r} with overrides "
                              f"{_shown_short(overrides)} does not load: {exc}") from None


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


# ============================================================================ config.json: one schema


def env_record(env_id: str, kwargs: dict | None = None) -> dict:
    """config.json's ``system`` for a gymnasium env: its id and keyword arguments (``kind`` "gymnasium")."""
    return {"name": env_id, "kind": "gymnasium", "kwargs": to_jsonable(dict(kwargs or {}))}


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
