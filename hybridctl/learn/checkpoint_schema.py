"""The shape of a checkpoint: its file names, its format number, its one error and the JSON schemas.

Every file of a checkpoint is data from someone else: :func:`check_schema` checks config.json,
progress.json and normalization.json against :data:`SCHEMAS` (one place for every shape check;
an error names the file and the key). :mod:`hybridctl.learn.checkpoint` reads and writes the files.
"""

from __future__ import annotations

import json
import math
import numbers
from pathlib import Path
from typing import Any, Callable, Iterable

from ..io import to_jsonable
from ..limits import MAX_HIDDEN_UNITS, MAX_NUM_ENVS
from ..systems.spec import SYSTEM_NAME

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


FORCE_HINT = "pass force=True (CLI: --force) to load it anyway"


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
