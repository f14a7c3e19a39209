"""The shape of a checkpoint: its file names, its format number, its one error and the JSON schemas.

Every file of a checkpoint is data from someone else: :func:`check_schema` checks config.json,
progress.json and normalization.json against :data:`SCHEMAS` (one place for every shape check;
an error names the file and the key). :mod:`hybridctl.learn.checkpoint` reads and writes the files.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import stat
from pathlib import Path
from typing import Any, Callable, Iterable

from ..io import to_jsonable
from ..limits import (MAX_CHECKPOINT_STRING, MAX_HIDDEN_UNITS, MAX_NETWORK_PARAMETERS, MAX_NUM_ENVS,
                      MAX_SIMULATION_STEPS, MAX_SPEC_BYTES, memory_budget)
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
    _check_strings(path, doc)
    if Path(path).name == CONFIG_FILE:
        _check_networks(path, doc, algorithm)


BYTES_PER_PARAMETER = 4
"""Bytes of one float32 weight."""
NETWORK_COPIES = {"SAC": 5, "SSAC": 5}
"""Copies of a recorded network a loader may hold at once (SAC's actor, two critics, their two targets)."""


def _integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def network_parameters(n_in: int, widths: Iterable[int], n_out: int, per_layer: int = 1) -> int:
    """Weights and biases of the fully connected network n_in -> widths -> n_out (``per_layer`` times
    each hidden layer's, e.g. 3 for a GRU's gates); exact Python integers, so no size overflows."""
    sizes = [n_in, *widths, n_out]
    return sum(per_layer * (a + 1) * b for a, b in zip(sizes, sizes[1:]))


def _recorded_networks(doc: dict, algorithm) -> list[tuple[str, int, int]]:
    """(the keys that size it, parameters, copies) of each network config.json ``doc`` describes."""
    config = doc.get("config") if isinstance(doc.get("config"), dict) else {}
    dims = [doc.get(k) for k in ("obs_dim", "action_dim")]
    n_obs, n_act = (d if _integer(d) and d > 0 else 1 for d in dims)
    out = []
    layers, width = config.get("hidden_layers"), config.get("hidden_size")
    if algorithm in NETWORK_COPIES and _integer(layers) and _integer(width) and layers >= 0 and width > 0:
        out.append(("'obs_dim', 'action_dim', 'config.hidden_layers' x 'config.hidden_size'",
                    network_parameters(n_obs + n_act, [width] * layers, 2 * n_act), NETWORK_COPIES[algorithm]))
    gate = doc.get("gate") if isinstance(doc.get("gate"), dict) else {}
    if isinstance(gate.get("hidden"), list) and all(_integer(w) and w > 0 for w in gate["hidden"]):
        out.append(("'obs_dim', 'gate.hidden'", network_parameters(n_obs + 1, gate["hidden"], 2), 1))
    policy = doc.get("policy") if isinstance(doc.get("policy"), dict) else {}
    hidden = policy.get("hidden")
    if isinstance(hidden, list) and all(_integer(w) and w > 0 for w in hidden):
        p_in, p_out = (policy.get(k) if _integer(policy.get(k)) and policy.get(k) > 0 else 1
                       for k in ("obs_dim", "act_dim"))
        out.append(("'policy.obs_dim', 'policy.hidden', 'policy.act_dim'",
                    network_parameters(p_in, hidden, p_out, per_layer=3 if policy.get("kind") == "gru" else 1), 1))
    if _integer(policy.get("n_params")):
        out.append(("'policy.n_params'", policy["n_params"], 1))
    return out


def _check_networks(path: Path, doc: dict, algorithm) -> None:
    """Refuse a config.json whose recorded networks would be too large to build, before any is allocated:
    parameters above MAX_NETWORK_PARAMETERS, or their copies' bytes above the memory budget."""
    budget = memory_budget()
    for keys, parameters, copies in _recorded_networks(doc, algorithm):
        nbytes = parameters * copies * BYTES_PER_PARAMETER
        if parameters > MAX_NETWORK_PARAMETERS or nbytes > budget:
            raise CheckpointError(f"{path}: {keys} describe a network of {parameters:,} parameters "
                                  f"({nbytes / 2**30:.3g} GiB for {copies} cop{'ies' if copies > 1 else 'y'}); "
                                  f"the limit is "
                                  f"{MAX_NETWORK_PARAMETERS:,} parameters (hybridctl.limits.MAX_NETWORK_PARAMETERS) "
                                  f"within {budget / 2**30:.3g} GiB of memory")


def _check_strings(path: Path, doc: Any) -> None:
    """Refuse a string (a value or a key) longer than MAX_CHECKPOINT_STRING anywhere in ``doc``, naming where."""
    stack = [("", doc)]
    while stack:
        where, value = stack.pop()
        if isinstance(value, str) and len(value) > MAX_CHECKPOINT_STRING:
            raise CheckpointError(f"{path}: {where or 'the document'!r} is a string of {len(value):,} characters, "
                                  f"above the limit of {MAX_CHECKPOINT_STRING:,} "
                                  "(hybridctl.limits.MAX_CHECKPOINT_STRING)")
        if isinstance(value, dict):
            for key, item in value.items():
                name = f"{where}.{key}" if where else str(key)
                if len(str(key)) > MAX_CHECKPOINT_STRING:
                    raise CheckpointError(f"{path}: a key of {where or 'the document'!r} has {len(str(key)):,} "
                                          f"characters, above the limit of {MAX_CHECKPOINT_STRING:,} "
                                          "(hybridctl.limits.MAX_CHECKPOINT_STRING)")
                stack.append((name, item))
        elif isinstance(value, list):
            stack.extend((f"{where}[{i}]", item) for i, item in enumerate(value))


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


# ============================================================================ recorded env keyword arguments
RENDER_MODES = (None, "rgb_array")
"""The render modes a recorded env may ask for: none, or frames as arrays; never a window ("human")."""
GYM_MAKE_KEYS = {"max_episode_steps": lambda v: _integer(v) and 1 <= v <= MAX_SIMULATION_STEPS,
                 "disable_env_checker": lambda v: isinstance(v, bool)}
"""The keywords of ``gymnasium.make`` itself a record may set (with their test); the others it takes
(``autoreset``, ``apply_api_compatibility``, ...) change what the env is and are refused."""
REFUSED_KEYS = ("autoreset", "apply_api_compatibility", "order_enforce", "kwargs", "id")
MAX_ENV_KWARGS = 64
"""Keyword arguments of one recorded env."""


def _plain_value(value) -> bool:
    """A scalar setting (None, a bool, a finite number, a short string) or a short list of finite numbers."""
    if value is None or isinstance(value, bool) or _is_number(value):
        return True
    if isinstance(value, str):
        return len(value) <= MAX_CHECKPOINT_STRING
    return isinstance(value, list) and len(value) <= 1000 and all(_is_number(v) for v in value)


def check_env_kwargs(value: Any, file, key: str = "env_kwargs") -> dict | None:
    """``value`` (``file``'s ``key``: an env's keyword arguments) if every one is safe to hand to
    ``gymnasium.make``; else :class:`CheckpointError` naming the file, the key and the rule.

    Accepted: None, or an object of at most :data:`MAX_ENV_KWARGS` string keys whose values are plain
    settings (:func:`_plain_value`); ``render_mode`` one of :data:`RENDER_MODES` (never "human": a window
    the run would wait on, or abort in GLFW without a display); of ``gymnasium.make``'s own keywords
    only :data:`GYM_MAKE_KEYS`; a keyword naming a file (``*_file``, ``*_path``) only a regular file of
    at most MAX_SPEC_BYTES, checked with ``os.stat`` before anything opens it.
    """
    if value is None:
        return None
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise CheckpointError(f"{file}: {key!r} must be null or an object of keyword arguments, got "
                              f"{_kind(value)} {_shown_short(value)}")
    if len(value) > MAX_ENV_KWARGS:
        raise CheckpointError(f"{file}: {key!r} has {len(value)} keyword arguments, above the limit of "
                              f"{MAX_ENV_KWARGS}")
    for name, item in value.items():
        where = f"{file}: {key}.{name[:60]!r}"
        if name == "render_mode":
            if item not in RENDER_MODES:
                raise CheckpointError(f"{where} is {_shown_short(item)}; a recorded env renders as null or "
                                      f"'rgb_array' only (never 'human': a window)")
        elif name in GYM_MAKE_KEYS:
            if not GYM_MAKE_KEYS[name](item):
                raise CheckpointError(f"{where} is {_shown_short(item)}, not a value gymnasium.make accepts here")
        elif name in REFUSED_KEYS or not name.isidentifier():
            raise CheckpointError(f"{where}: not a keyword argument a recorded env may set")
        elif not _plain_value(item):
            raise CheckpointError(f"{where} must be null, true/false, a finite number, a string of at most "
                                  f"{MAX_CHECKPOINT_STRING:,} characters or a list of finite numbers, got "
                                  f"{_shown_short(item)}")
        elif name.endswith(("_file", "_path")) and item is not None:
            _check_named_file(where, item)
    return value


def _check_named_file(where: str, item) -> None:
    """A keyword's file: a regular file of at most MAX_SPEC_BYTES (os.stat before any open)."""
    try:
        info = os.stat(item) if isinstance(item, str) else None
    except OSError:
        info = None
    if info is None or not stat.S_ISREG(info.st_mode):
        raise CheckpointError(f"{where} is {_shown_short(item)}, not a regular file")
    if info.st_size > MAX_SPEC_BYTES:
        raise CheckpointError(f"{where} names a file of {info.st_size:,} bytes, above the limit of "
                              f"{MAX_SPEC_BYTES:,} (hybridctl.limits.MAX_SPEC_BYTES)")
